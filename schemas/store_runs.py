"""Run logs: ``runs/<run_id>.json`` (start, end, counts, progress, errors of one run)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from schemas.calibration_file import write_json_atomic
from schemas.store_io import jsonable


class RunLogs:
    """The run logs of the store rooted at ``self.root``."""

    root: Path

    @property
    def runs_dir(self) -> Path:
        return self.root / "runs"

    def write_run(self, run_id: str, doc: dict[str, Any]) -> Path:
        path = self.runs_dir / f"{run_id}.json"
        write_json_atomic(path, jsonable(doc))
        return path

    def read_run(self, run_id: str) -> dict[str, Any]:
        return json.loads((self.runs_dir / f"{run_id}.json").read_text())

    def runs(self) -> list[Path]:
        return sorted(self.runs_dir.glob("*.json")) if self.runs_dir.is_dir() else []
