"""Statistics of a processed dataset: the paper's histograms of components per shape (Fig. "data
statistics"), with what each merge rule did and how many shapes were discarded and why.

Everything is read from ``dataset.json`` (``info`` written by preprocessing), so statistics never
need the arrays.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

HISTOGRAM_PNG = "components_histogram.png"
TABLE_TXT = "data_stats.txt"
SUMMARY_JSON = "data_stats.json"


def load_info(processed: Path) -> dict[str, Any]:
    """The ``dataset.json`` of a processed folder (info, shapes and hash)."""
    path = Path(processed) / "dataset.json"
    if not path.is_file():
        raise FileNotFoundError(f"processed dataset file missing: {path} "
                                "(run `complementme data preprocess`)")
    info = json.loads(path.read_text())
    for key in ("components_histogram", "per_category", "merge_counts", "counts", "rejected", "config"):
        if key not in info:
            raise ValueError(f"{path}: no {key!r} entry (written by an older or different preprocessing)")
    return info


def summarize(info: dict[str, Any]) -> dict[str, Any]:
    """Per-category totals: shapes, kept, discarded (by reason) and the component histogram."""
    cats = sorted(set(info["per_category"]) | set(info["components_histogram"]))
    rows = []
    for cat in cats:
        per = info["per_category"].get(cat, {"kept": 0, "rejected": {}})
        hist = {int(k): v for k, v in info["components_histogram"].get(cat, {}).items()}
        kept = {int(k): v for k, v in info.get("components_histogram_kept", {}).get(cat, {}).items()}
        rows.append({"category": cat, "shapes": per["kept"] + sum(per["rejected"].values()),
                     "kept": per["kept"], "discarded": sum(per["rejected"].values()),
                     "discarded_by_reason": dict(sorted(per["rejected"].items())),
                     "histogram": dict(sorted(hist.items())), "histogram_kept": dict(sorted(kept.items()))})
    reasons: dict[str, int] = {}
    for r in info["rejected"]:
        reasons[r["code"]] = reasons.get(r["code"], 0) + 1
    return {"categories": rows, "merge_counts": info["merge_counts"], "counts": info["counts"],
            "discarded_by_reason": dict(sorted(reasons.items())),
            "min_components": info["config"]["min_components"],
            "max_components": info["config"]["max_components"]}


def _pairs(counts: dict[str, int]) -> str:
    return ", ".join(f"{k} {v}" for k, v in counts.items())


def format_table(summary: dict[str, Any]) -> str:
    """The summary as plain text: one row per category, histogram columns 1..max seen."""
    rows = summary["categories"]
    top = max([max(r["histogram"], default=0) for r in rows] + [summary["max_components"]])
    head = f"{'category':<16}{'shapes':>8}{'kept':>7}{'disc.':>7}  "\
        + "".join(f"{n:>5}" for n in range(1, top + 1))
    lines = [f"Components per shape (kept: {summary['min_components']}..{summary['max_components']} "
             "components, connected contact graph)", head, "-" * len(head)]
    for r in rows:
        hist = "".join(f"{r['histogram'].get(n, 0):>5}" for n in range(1, top + 1))
        lines.append(f"{r['category']:<16}{r['shapes']:>8}{r['kept']:>7}{r['discarded']:>7}  {hist}")
    counts = summary["counts"]
    lines += ["", f"shapes in: {counts['shapes_in']}, kept: {counts['kept']}, "
              f"discarded: {counts['rejected']}; pieces in: {counts['pieces_in']}, "
              f"components out: {counts['components']}",
              "merges (unions done): " + _pairs(summary["merge_counts"]),
              "discarded by reason: " + (_pairs(summary["discarded_by_reason"]) or "none")]
    lines += [f"  {r['category']}: {_pairs(r['discarded_by_reason'])}"
              for r in rows if r["discarded_by_reason"]]
    return "\n".join(lines) + "\n"


def plot_histograms(summary: dict[str, Any], path: Path) -> None:
    """One bar chart per category: kept shapes in blue, discarded ones stacked in grey."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = summary["categories"]
    lo, hi = summary["min_components"], summary["max_components"]  # the kept range, shaded
    top = max([max(r["histogram"], default=0) for r in rows] + [hi])
    cols = min(4, max(1, len(rows)))
    nrows = (len(rows) + cols - 1) // cols
    fig, axes = plt.subplots(nrows, cols, figsize=(3.2 * cols, 2.6 * nrows), squeeze=False)
    xs = list(range(1, top + 1))
    for ax, r in zip(axes.flat, rows, strict=False):
        kept = [r["histogram_kept"].get(n, 0) for n in xs]
        dropped = [r["histogram"].get(n, 0) - k for n, k in zip(xs, kept, strict=True)]
        ax.bar(xs, kept, color="#4c72b0")
        ax.bar(xs, dropped, bottom=kept, color="#c0c0c0")
        ax.axvspan(lo - 0.5, hi + 0.5, color="#4c72b0", alpha=0.06, lw=0)
        ax.set_title(f"{r['category']} ({r['shapes']})\n{r['discarded']} discarded", fontsize=9)
        ax.set_xticks(xs)
        # Explicit limits: the shaded span would otherwise pin the y range to the tallest bar.
        ax.set_ylim(0, 1.15 * max([*(r["histogram"].get(n, 0) for n in xs), 1]))
        ax.tick_params(labelsize=7)
    for ax in list(axes.flat)[len(rows):]:
        ax.axis("off")
    fig.supxlabel("components per shape (blue: kept, grey: discarded)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def write_stats(processed: Path, out: Path) -> dict[str, Any]:
    """Write the histogram PNG, the text table and a JSON summary to ``out``; returns the summary."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    summary = summarize(load_info(processed))
    (out / TABLE_TXT).write_text(format_table(summary))
    (out / SUMMARY_JSON).write_text(json.dumps(summary, indent=1, sort_keys=True) + "\n")
    plot_histograms(summary, out / HISTOGRAM_PNG)
    return summary
