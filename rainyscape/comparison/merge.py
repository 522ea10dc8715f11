"""Several rs-bench results files as one benchmark: a set's rows are often trained apart (the
plain field one day, a rain method the next, a slow scene in a run of its own), and its gap
shares are only right when computed over all of them. Merging the files lets rs-bench's own
tables (``tables.markdown_report``) compute them, rather than a person by hand.

Only the main tables' finished cells are merged (an ablation's cells belong to their own
run). A cell that two files both hold is kept once when both trained the same config (the
same fingerprint: runs are deterministic) and refused otherwise, naming both files.
"""

from __future__ import annotations

from pathlib import Path

from rainyscape.comparison.matrix import CEILING, Cell
from rainyscape.errors import DataError


def recorded_cell(key: str, record: dict) -> Cell:
    """The cell a results file's record describes (its scene folder is not recorded: "")."""
    label = record.get("label") or record["method"]
    return Cell(key, record["scene"], "", record["method"], list(record.get("overrides", [])), label,
                clean=label.endswith(CEILING))


def merge_results(files: list[tuple[Path, dict]]) -> tuple[list[Cell], dict]:
    """The finished main-table cells of ``files`` ((path, results) in order) and one results
    dict holding them, in the order first seen, with each file's command and machine."""
    cells: list[Cell] = []
    merged: dict = {"cells": {}, "oracle": {}, "budget_mismatches": []}
    source: dict[str, Path] = {}
    for path, results in files:
        for key, record in results["cells"].items():
            if key.startswith("ablation/") or record.get("status") != "finished":
                continue
            if key in merged["cells"]:
                if merged["cells"][key].get("fingerprint") != record.get("fingerprint"):
                    raise DataError(f"{path}: cell {key} was also trained, with another config, in "
                                    f"{source[key]}; merge one of the two")
                continue
            if "scene" not in record or "method" not in record:
                raise DataError(f"{path}: cell {key} records no scene or method")
            merged["cells"][key], source[key] = record, path
            cells.append(recorded_cell(key, record))
        for scene, rows in results.get("oracle", {}).items():
            merged["oracle"].setdefault(scene, rows)
        merged["budget_mismatches"] += [m for m in results.get("budget_mismatches", [])
                                        if m not in merged["budget_mismatches"]]
    machines = [r.get("machine", {}) for _, r in files]
    merged["machine"] = machines[0] if all(m == machines[0] for m in machines) else {
        "cpu": " / ".join(sorted({m.get("cpu", "?") for m in machines})), "cores": "?"}
    merged["command"] = "; ".join(f"{r.get('command', '?')} ({p.name})" for p, r in files)
    merged["updated"] = max((str(r.get("updated", "")) for _, r in files), default="")
    return cells, merged
