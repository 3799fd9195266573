"""`complementme evaluate`: the benchmark of the paper's Section 6.2 on the shipped artifacts.

A thin wrapper: parse options into ``BenchmarkSettings`` and call ``run.run_benchmark``. Torch
and the evaluation modules are imported inside the command, so the CLI starts fast.
"""

from __future__ import annotations

import shlex
import sys
from pathlib import Path
from typing import Optional

import typer

QUICK_OUT = Path("runs/benchmark-quick")


def default_report(out: Path | None, quick: bool) -> Path:
    """Where ``evaluate`` writes its Markdown report without ``--report``: beside results.json when
    ``--out`` or ``--quick`` names the folder, else the committed docs/benchmark.md. Why: an
    exploratory run with its own ``--out`` must never overwrite the committed report."""
    if out is None and not quick:
        return Path("docs/benchmark.md")
    return (out or QUICK_OUT) / "benchmark.md"


def evaluate_command(
    artifacts: Path = typer.Option(Path("exported"), "--artifacts", help="Artifact folder (Ours)."),
    run: Path = typer.Option(Path("runs/shipped"), "--run", "--run-dir",
                             help="The training run's folder: its split.json is checked against the "
                                  "catalog, and the fixed-embedding baseline caches its weights there "
                                  "unless --fixed-cache names a folder."),
    data: Optional[Path] = typer.Option(None, "--data",  # noqa: UP045 (typer needs Optional on 3.10)
                                        help="Processed dataset (default: the path in the manifest)."),
    out: Optional[Path] = typer.Option(None, "--out",  # noqa: UP045
                                       help="Folder for results.json and the PNG charts "
                                            "(default: docs/benchmark; runs/benchmark-quick with --quick)."),
    report: Optional[Path] = typer.Option(None, "--report",  # noqa: UP045
                                          help="Markdown report (default: docs/benchmark.md; "
                                               "<out>/benchmark.md with --out or --quick)."),
    quick: bool = typer.Option(False, "--quick", help="CI mode: a few queries per category, a token "
                                                      "fixed-embedding training (minutes -> seconds)."),
    seed: int = typer.Option(0, "--seed", help="Seed of the queries, samples and baselines."),
    queries: int = typer.Option(100, "--queries", help="Queries per category and setting (paper: 100)."),
    query_split: str = typer.Option("test", "--query-split",
                                    help="Retrieval queries from the held-out shapes ('test') or from "
                                         "the training shapes ('train': to choose service settings, "
                                         "given as COMPLEMENTME_* variables, without the held-out ones)."),
    placement_queries: int = typer.Option(100, "--placement-queries",
                                          help="Placement queries per category and split."),
    plausibility_queries: int = typer.Option(50, "--plausibility-queries",
                                             help="All-but-one queries per category whose top-1 is "
                                                  "placed and checked for contact."),
    robustness: bool = typer.Option(True, "--robustness/--no-robustness",
                                    help="Also score Ours on the all-but-one queries perturbed (other "
                                         "proportions, rotated, off frame, noisy, holed), with and "
                                         "without the category (about a minute)."),
    methods: str = typer.Option("random,ck10,fixed,likelihood,ours", "--methods",
                                help="Comma-separated subset of random, ck10, fixed, likelihood (the "
                                     "paper's ranking: Ours without the complement check, in likelihood "
                                     "order), ranked (Ours with COMPLEMENTME_SUGGEST_ORDER=likelihood), "
                                     "ours."),
    pool: str = typer.Option("category", "--pool", help="Candidate pool: 'category' (other shapes of the "
                                                         "query's category) or 'all' (other shapes)."),
    collapse_duplicates: bool = typer.Option(True, "--collapse-duplicates/--keep-duplicates",
                                             help="Show one part per near-duplicate group, as the service."),
    dense_points: int = typer.Option(1024, "--dense-points", help="Surface samples per part from its mesh."),
    ck10_shapes: int = typer.Option(5, "--ck10-shapes", help="CK10: similar shapes whose parts come first."),
    fixed_steps: int = typer.Option(3000, "--fixed-steps", help="Fixed-embedding baseline: steps of g."),
    fixed_minutes: float = typer.Option(30.0, "--fixed-minutes",
                                        help="Fixed-embedding baseline: a wall-clock guard that stops a far "
                                             "slower training than planned (its rows then differ)."),
    fixed_dim: int = typer.Option(50, "--fixed-dim", help="Fixed-embedding baseline: PCA dimensions."),
    fixed_cache: Optional[Path] = typer.Option(  # noqa: UP045
        None, "--fixed-cache", help="Folder of the fixed-embedding baseline's cached weights (default: the "
                                    "run folder). The committed benchmark keeps them beside its results, "
                                    "so that a re-run on any host reads the same baseline."),
    contact_tolerance: float = typer.Option(0.02, "--contact-tolerance",
                                            help="Gap or depth (unit radius) of an implausible placement."),
    contact_samples: int = typer.Option(256, "--contact-samples",
                                        help="Surface samples per part in contact tests."),
    threads: int = typer.Option(0, "--threads", help="Torch threads (0 = torch's default)."),
    details: bool = typer.Option(False, "--details", help="Also write every query's record (queries.json)."),
    progress: bool = typer.Option(True, "--progress/--no-progress", help="Show progress bars."),
    notes: Optional[Path] = typer.Option(None, "--notes",  # noqa: UP045
                                         help="Markdown file rendered as the report's Analysis section "
                                              "(kept in results.json)."),
    database: str = typer.Option("components", "--database", help=(
        "The parts ranked and removed: 'components' (the catalog's, as served) or 'grouped' (each "
        "shape's components of one label grouped into one part, for the queries and the database: "
        "the paper's Section 6.2 protocol; the artifacts' networks exported over the grouped data "
        "into <run>/grouped/, reused while model and data are the same; labels read to measure only)."),
        case_sensitive=False),
    render_only: bool = typer.Option(False, "--render-only",
                                     help="Re-render the report and charts from <out>/results.json "
                                          "(with --notes, replacing its notes) without running anything."),
) -> None:
    """Benchmark the shipped model against Random, CK10 and a fixed embedding (paper Tables 1-4)."""
    from training.evaluate.evaluation import ContactSettings, RetrievalSettings
    from training.evaluate.fixed_embedding import FixedSettings
    from training.evaluate.run import BenchmarkSettings, quick_settings, run_benchmark

    out_dir = out or (QUICK_OUT if quick else Path("docs/benchmark"))
    report_path = report or default_report(out, quick)
    notes_text = None
    if notes is not None:
        if not notes.is_file():
            typer.echo(f"error: --notes {notes}: no such file", err=True)
            raise typer.Exit(code=2)
        notes_text = notes.read_text()
    if render_only:
        from training.evaluate.run import rerender

        try:
            rerender(out_dir, report_path, notes_text, notes)
        except (ValueError, FileNotFoundError) as exc:
            typer.echo(f"error: {exc}", err=True)
            raise typer.Exit(code=2) from exc
        return
    settings = BenchmarkSettings(
        artifacts=artifacts, run=run, fixed_cache=fixed_cache, database=database, data=data, out=out_dir,
        report=report_path,
        seed=seed,
        queries_per_category=queries, query_split=query_split,
        placement_queries_per_category=placement_queries,
        plausibility_queries_per_category=plausibility_queries, robustness=robustness,
        dense_points=dense_points,
        methods=tuple(m.strip() for m in methods.split(",") if m.strip()), ck10_shapes=ck10_shapes,
        threads=threads, details=details, progress=progress, notes=notes_text,
        command=" ".join(["complementme", *(shlex.quote(a) for a in sys.argv[1:])]),
        retrieval=RetrievalSettings(pool_scope=pool, collapse_duplicates=collapse_duplicates),
        contact=ContactSettings(tolerance=contact_tolerance, samples=contact_samples),
        fixed=FixedSettings(dim=fixed_dim, steps=fixed_steps, minutes=fixed_minutes))
    if quick:
        settings = quick_settings(settings)
    try:
        run_benchmark(settings)
    except (ValueError, FileNotFoundError, RuntimeError) as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(code=2) from exc


def evaluate_assembly_command(
    artifacts: Path = typer.Option(Path("exported"), "--artifacts", help="Artifact folder."),
    out: Path = typer.Option(Path("docs/assembly"), "--out", help="Folder for results.json."),
    report: Optional[Path] = typer.Option(Path("docs/modeling.md"), "--report",  # noqa: UP045
                                          help="Markdown file whose assembly-evaluation block is rewritten."),
    no_report: bool = typer.Option(False, "--no-report", help="Write results.json only."),
    seed: int = typer.Option(0, "--seed", help="Seed of the start parts and the sampler."),
    starts: Optional[int] = typer.Option(None, "--starts", help=(  # noqa: UP045
        "Start parts per category (unset: the evaluation's default, AssemblyEvalSettings."
        "starts_per_category).")),
    split: str = typer.Option("test", "--split", help=(
        "Shapes the start parts come from: test (held out, reported) or train (for tuning the "
        "assembly's settings; the start's own shape is still excluded).")),
    strategies: str = typer.Option("greedy", "--strategies", help="Comma-separated: greedy, sample."),
    temperature: float = typer.Option(1.0, "--temperature", help="Temperature of the sampled runs."),
    max_parts: Optional[int] = typer.Option(None, "--max-parts",  # noqa: UP045
                                            help="Parts to add (default: the service's setting)."),
    contact: bool = typer.Option(True, "--contact/--no-contact",
                                 help="Measure floating and interpenetration (exact, slower)."),
    contact_tolerance: float = typer.Option(0.02, "--contact-tolerance", help="Gap or depth that counts."),
    pictures: int = typer.Option(0, "--pictures", help=(
        "Runs to draw per category, into <out>/<category>.png, linked from the report (0: none).")),
    progress: bool = typer.Option(True, "--progress/--no-progress", help="Show a progress bar."),
) -> None:
    """Automatic assembly from held-out start parts: complete, stacked, empty, floating runs.

    Labels are read to measure only."""
    from training.evaluate.assembly_eval import AssemblyEvalSettings, run_assembly_evaluation

    settings = AssemblyEvalSettings(
        artifacts=artifacts, out=out, report=None if no_report else report, seed=seed,
        **({} if starts is None else {"starts_per_category": starts}), split=split,
        strategies=tuple(x.strip() for x in strategies.split(",") if x.strip()),
        temperature=temperature, max_parts=max_parts, contact=contact, contact_tolerance=contact_tolerance,
        pictures=pictures, progress=progress,
        command=" ".join(["complementme", *(shlex.quote(a) for a in sys.argv[1:])]))
    try:
        run_assembly_evaluation(settings)
    except (ValueError, FileNotFoundError) as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(code=2) from exc


def evaluate_frames_command(
    artifacts: Path = typer.Option(Path("exported"), "--artifacts", help="Artifact folder."),
    out: Optional[Path] = typer.Option(None, "--out", help="Folder for results.json."),  # noqa: UP045
    shapes: int = typer.Option(80, "--shapes", min=1, help="Held-out partial shapes per set."),
    seed: int = typer.Option(0, "--seed", help="Seed of the shapes and their frames."),
    split: str = typer.Option("test", "--split", help="Split of the catalog's shapes: test or train."),
) -> None:
    """Frame fitting of partial uploads: how often each scoring rule finds the frame.

    Labels are read to build the second set only."""
    from training.evaluate.frames_eval import FrameEvalSettings, markdown, run_frame_evaluation

    try:
        report = run_frame_evaluation(FrameEvalSettings(artifacts=artifacts, shapes=shapes, seed=seed,
                                                        split=split, out=out))
    except (ValueError, FileNotFoundError) as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(code=2) from exc
    typer.echo(f"{report['model_version']}, {report['hypotheses']}, radius prior {report['radius_prior']}")
    typer.echo(markdown(report))


def evaluate_real_command(
    data: Path = typer.Option(Path("data/real-test/processed"), "--data", help=(
        "Processed folder of an outside collection (`data sweethome3d`, `data ingest`, `data preprocess`).")),
    artifacts: Path = typer.Option(Path("exported"), "--artifacts", help="Artifact folder."),
    out: Optional[Path] = typer.Option(None, "--out", help="Folder for results.json."),  # noqa: UP045
    queries_per_shape: int = typer.Option(4, "--queries-per-shape", min=1,
                                          help="Components taken away per shape."),
    seed: int = typer.Option(0, "--seed", help="Seed of the queries and the chance baseline."),
) -> None:
    """Suggestions on shapes nobody here made, beside as many of the catalog's held-out shapes.

    Label-free measures: the inferred category against the folders, warnings, and how far the
    placed suggestions lie from the component taken away."""
    from training.evaluate.real_shapes import RealEvalSettings, markdown, run_real_evaluation

    try:
        report = run_real_evaluation(RealEvalSettings(data=data, artifacts=artifacts, out=out,
                                                      queries_per_shape=queries_per_shape, seed=seed))
    except (ValueError, FileNotFoundError) as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(code=2) from exc
    typer.echo(f"{report['model_version']} on {report['data']}")
    typer.echo(markdown(report))


def register_evaluate_command(app: typer.Typer) -> None:
    """Add `evaluate`, `evaluate-assembly`, `evaluate-frames` and `evaluate-real` to the root CLI."""
    app.command("evaluate")(evaluate_command)
    app.command("evaluate-assembly")(evaluate_assembly_command)
    app.command("evaluate-frames")(evaluate_frames_command)
    app.command("evaluate-real")(evaluate_real_command)
