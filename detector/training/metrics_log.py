"""A run's ``metrics.csv``: one row per step, cut back to the checkpoint's step on resume, and read back with
numbers parsed."""

from __future__ import annotations

import csv
from pathlib import Path



class MetricsLog:
    """``metrics.csv`` (columns ``fields``): one row per step; on resume the rows after the checkpoint's step
    are dropped."""

    def __init__(self, path: Path, keep_until: int | None, fields: list[str]):
        self.path = path
        rows = []
        if keep_until is not None and path.is_file():
            with path.open(newline="") as f:
                rows = [r for r in csv.DictReader(f) if int(r["step"]) <= keep_until]
        self.file = path.open("w", newline="")
        self.writer = csv.DictWriter(self.file, fieldnames=fields)
        self.writer.writeheader()
        self.writer.writerows(rows)
        self.file.flush()

    def write(self, row: dict) -> None:
        """Append one row (floats with 9 significant digits) and flush."""
        self.writer.writerow({k: (f"{v:.9g}" if isinstance(v, float) else v) for k, v in row.items()})
        self.file.flush()

    def close(self) -> None:
        self.file.close()


def read_metrics(path: str | Path) -> list[dict]:
    """Rows of a ``metrics.csv`` with numbers parsed (empty cells become None)."""
    def num(v: str):
        if v == "":
            return None
        try:
            return int(v)
        except ValueError:
            try:
                return float(v)
            except ValueError:
                return v

    with Path(path).open(newline="") as f:
        return [{k: num(v) for k, v in r.items()} for r in csv.DictReader(f)]
