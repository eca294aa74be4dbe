#!/usr/bin/env bash
# Lint and format check (configuration: [tool.ruff] in pyproject.toml). Checks only, never
# rewrites: `ruff check --fix .` and `ruff format .` are for a developer to run and review.
# Runs both checks and fails if either finds something.
set -uo pipefail
cd "$(dirname "$0")/.."
RUFF="${RUFF:-$( [ -x .venv/bin/ruff ] && echo .venv/bin/ruff || echo ruff )}"
status=0
"$RUFF" check . || status=1
"$RUFF" format --check . || status=1
exit $status
