"""What exists, for one-line user errors: "lot 'L9' not in the results store (lots: L1, L2)".

Read from directory names and the store's small tables only, so that a wrong lot or unit is
answered in well under a second, before Prefect starts."""

from __future__ import annotations

from pathlib import Path

from flows.cli import CliError

MAX_LISTED = 12


def listing(names: list[str] | set[str], max_listed: int = MAX_LISTED) -> str:
    """ "A, B, C" (sorted), "none", or the first ``max_listed`` and how many in all."""
    names = sorted({str(n) for n in names})
    if not names:
        return "none"
    if len(names) <= max_listed:
        return ", ".join(names)
    return ", ".join(names[:max_listed]) + f", ... ({len(names)} in all)"


def units_under(dataset: str | Path) -> str:
    """The units of a hive dataset (``lot=*/unit=*`` directory names), as a listing."""
    root = Path(dataset)
    units = {p.name.split("=", 1)[1] for p in root.glob("lot=*/unit=*") if p.is_dir()}
    return listing(units)


def store_units(results: str | Path) -> dict[str, set[str]]:
    """lot -> units of a results store (its units table, else its calibration folders)."""
    from schemas.results_store import ResultsStore

    store = ResultsStore(Path(results))
    out: dict[str, set[str]] = {}
    if store.has_table("units"):
        df = store.read("units", columns=["lot", "unit"])
        for lot, unit in zip(df["lot"].astype(str), df["unit"].astype(str)):
            out.setdefault(lot, set()).add(unit)
    return out


def check_store(results: str | Path) -> dict[str, set[str]]:
    """The store's lots and units; CliError when ``results`` holds no results store."""
    from schemas.results_store import ResultsStore

    root = Path(results)
    if not root.is_dir():
        raise CliError(f"results store {root} does not exist; run 'mimucal nightly' first")
    store = ResultsStore(root)
    if not store.has_table("units") and not store.has_table("summary"):
        raise CliError(f"{root} is not a results store (no units table); run 'mimucal nightly' first")
    return store_units(root)


def check_lot(results: str | Path, lot: str) -> None:
    """CliError naming the store's lots when ``lot`` is not one of them."""
    lots = check_store(results)
    if lot not in lots:
        raise CliError(f"lot {lot!r} is not in results store {results} (lots: {listing(lots)})")


def check_unit_in_dataset(dataset: str | Path, unit: str) -> None:
    """CliError naming the dataset's units when it has no ``unit=<unit>`` directory."""
    root = Path(dataset)
    if not any(p.is_dir() for p in root.glob(f"lot=*/unit={unit}")):
        raise CliError(f"unit {unit!r} is not in dataset {root} (units: {units_under(root)})")
