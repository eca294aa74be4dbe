"""Values the store keeps between runs that are not results: caches (outlier thresholds,
flag state, session digests; each rebuilt when missing or unreadable), the QA configuration
every later run applies, and each lot's QA context as its last re-flag left it."""

from __future__ import annotations

import json
from pathlib import Path
from urllib.parse import quote

import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from schemas.calibration_file import write_json_atomic
from schemas.store_io import jsonable, write_table_atomic, write_text_atomic

# schema metadata key of cache/flag_state.parquet holding its JSON document
FLAG_STATE_METADATA_KEY = b"mimucal.flag_state"


class StoreCaches:
    """The derived values and QA settings of the store rooted at ``self.root``."""

    root: Path

    @property
    def outlier_thresholds_path(self) -> Path:
        return self.root / "cache" / "outlier_thresholds.json"

    def read_outlier_thresholds(self) -> dict | None:
        """The outlier thresholds simulated by earlier runs (the document of a
        ``calib_core.outliers.ThresholdTable``), or None when absent or unreadable: a cache,
        never a source of truth (the values are recomputed when missing)."""
        try:
            return json.loads(self.outlier_thresholds_path.read_text())
        except (OSError, ValueError):
            return None

    def write_outlier_thresholds(self, doc: dict) -> None:
        write_json_atomic(self.outlier_thresholds_path, jsonable(doc))

    @property
    def flag_state_path(self) -> Path:
        return self.root / "cache" / "flag_state.parquet"

    def read_flag_state(self) -> tuple[pd.DataFrame, dict] | None:
        """The outlier flags' state kept by the last re-flag (flows.nightly): the rows the
        pooled scales come from, and a document (which lot files it describes, the pooled
        scales, the configuration). None when absent or unreadable: a cache, rebuilt by a
        full re-flag."""
        try:
            table = pq.read_table(self.flag_state_path)
            doc = json.loads((table.schema.metadata or {})[FLAG_STATE_METADATA_KEY])
        except (OSError, ValueError, KeyError, pa.ArrowException):
            return None
        return table.to_pandas(), doc

    def write_flag_state(self, rows: pd.DataFrame, doc: dict) -> None:
        table = pa.Table.from_pandas(rows, preserve_index=False)
        meta = {**(table.schema.metadata or {}), FLAG_STATE_METADATA_KEY: json.dumps(doc).encode()}
        write_table_atomic(table.replace_schema_metadata(meta), self.flag_state_path)

    # file digests of the sessions, by their stat (schemas.dataset.DigestCache)
    @property
    def digest_cache_path(self) -> Path:
        return self.root / "cache" / "session_digests.json"

    def read_digest_cache(self) -> dict:
        """A cache: empty when absent or unreadable (the files are hashed again)."""
        try:
            doc = json.loads(self.digest_cache_path.read_text())
        except (OSError, ValueError):
            return {}
        return doc.get("entries", {}) if isinstance(doc, dict) and doc.get("version") == 1 else {}

    def write_digest_cache(self, entries: dict) -> None:
        write_json_atomic(self.digest_cache_path, {"version": 1, "entries": entries})

    # the QA configuration (outlier options and limits) every later run applies
    @property
    def qa_config_path(self) -> Path:
        return self.root / "qa-config.toml"

    def read_qa_config(self) -> str | None:
        """The TOML text set by the last ``--config`` (None: the defaults)."""
        try:
            return self.qa_config_path.read_text()
        except FileNotFoundError:
            return None

    def write_qa_config(self, text: str | None) -> None:
        """Keep ``text`` as the QA configuration of every later run; None clears it."""
        if text is None:
            try:
                self.qa_config_path.unlink()
            except FileNotFoundError:
                pass
            return
        write_text_atomic(self.qa_config_path, text)

    # each lot's QA context (reference, thresholds, configuration) as its last re-flag left it
    def qa_lot_path(self, lot: str) -> Path:
        return self.root / "qa" / f"{quote(str(lot), safe='')}.json"

    def write_qa_lot(self, lot: str, doc: dict) -> None:
        write_json_atomic(self.qa_lot_path(lot), jsonable(doc))

    def read_qa_lot(self, lot: str) -> dict | None:
        try:
            return json.loads(self.qa_lot_path(lot).read_text())
        except (OSError, ValueError):
            return None
