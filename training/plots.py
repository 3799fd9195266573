"""Loss and validation logs of a run: CSV files appended as training goes, PNG plots drawn from them."""

from __future__ import annotations

import csv
import math
from pathlib import Path

LOSSES_CSV = "losses.csv"
VALIDATION_CSV = "validation.csv"
LOSSES_PNG = "losses.png"
VALIDATION_PNG = "validation.png"


class CsvLog:
    """Append rows to a CSV file; the header is written once and fixed by the first row's keys."""

    def __init__(self, path: Path, fields: list[str]):
        self.path = Path(path)
        self.fields = fields
        if not self.path.is_file() or self.path.stat().st_size == 0:
            with open(self.path, "w", newline="") as fh:
                csv.writer(fh).writerow(fields)

    def append(self, row: dict[str, float]) -> None:
        with open(self.path, "a", newline="") as fh:
            csv.writer(fh).writerow([_fmt(row.get(k, "")) for k in self.fields])


def _fmt(v: object) -> object:
    return f"{v:.6g}" if isinstance(v, float) else v


def read_csv(path: Path) -> dict[str, list[float]]:
    """Columns of a log as float lists (empty cells become NaN)."""
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    if not rows:
        return {}
    return {k: [float(r[k]) if r[k] not in ("", None) else math.nan for r in rows] for k in rows[0]}


def truncate_after(path: Path, step: int) -> None:
    """Drop rows logged after ``step`` (a resumed run re-does the steps after its checkpoint)."""
    path = Path(path)
    if not path.is_file():
        return
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    if not rows:
        return
    header, body = rows[0], rows[1:]
    keep = [r for r in body if r and float(r[0]) <= step]
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(header)
        w.writerows(keep)


def plot_columns(csv_path: Path, png_path: Path, columns: list[str], title: str, log_y: bool = False) -> None:
    """One subplot per column against ``step``; silently skips columns absent from the log."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    data = read_csv(csv_path)
    present = [c for c in columns if c in data and any(not math.isnan(v) for v in data[c])]
    if not present or "step" not in data:
        return
    fig, axes = plt.subplots(len(present), 1, figsize=(7, 2.2 * len(present)), sharex=True, squeeze=False)
    for ax, col in zip(axes[:, 0], present, strict=True):
        ax.plot(data["step"], data[col], lw=1)
        ax.set_ylabel(col, fontsize=8)
        if log_y and all(v > 0 for v in data[col] if not math.isnan(v)):
            ax.set_yscale("log")
        ax.grid(alpha=0.3)
    axes[-1, 0].set_xlabel("step")
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(png_path, dpi=90)
    plt.close(fig)
