"""Prefect flows, tasks and the ``mimucal`` command line. Orchestration only."""
