"""`complementme train`, `export`, `familiarity` and `category-head`.

The train command's options are generated from the ``TrainConfig`` and ``ModelConfig`` fields
(one ``--field-name`` per field, help text from the field's metadata), so a new config field is
a new option without touching this file. An option left out keeps the value of the preset or
``--config`` file; list-valued fields take comma-separated ints (``--point-layers 64,128,256``).

Torch is imported inside the commands only.
"""

from __future__ import annotations

import dataclasses
import inspect
import logging
from pathlib import Path
from typing import Any

import typer

from service.artifacts.layout import ArtifactError, read_manifest
from training.config import PRESETS, HeadFitSettings, ModelConfig, TrainConfig, field_types

log = logging.getLogger(__name__)

# Options of `train` that are not config fields.
_FIXED = ("preset", "config", "resume", "progress")


def _option_type(annotation: Any) -> Any:
    """The CLI type of a config field: tuples are read as comma-separated strings."""
    if getattr(annotation, "__origin__", None) is tuple:
        return str | None
    return annotation | None


def _config_fields() -> list[tuple[str, Any, str, tuple[str, ...]]]:
    """(name, annotation, help, aliases) of every TrainConfig and (flattened) ModelConfig field."""
    out = []
    for cls in (TrainConfig, ModelConfig):
        types_ = field_types(cls)
        for f in dataclasses.fields(cls):
            if f.name == "model":
                continue
            default = f.default if f.default is not dataclasses.MISSING else None
            shown = ",".join(map(str, default)) if isinstance(default, tuple) else default
            help_text = f"{f.metadata.get('help', '')} (default: {shown})"
            out.append((f.name, types_[f.name], help_text, tuple(f.metadata.get("aliases", ()))))
    return out


def _fail(exc: Exception) -> typer.Exit:
    typer.echo(f"error: {exc}", err=True)
    return typer.Exit(code=2)


def train_command(**kwargs: Any) -> None:
    """Train f, g and h jointly (see training/train.py); resumable, time-budgeted, torchrun-ready."""
    preset, config_file = kwargs.pop("preset"), kwargs.pop("config")
    resume, progress = kwargs.pop("resume"), kwargs.pop("progress")
    overrides = {k: v for k, v in kwargs.items() if v is not None}
    from training.config import resolve_config
    from training.train import config_for_resume, train

    try:
        if resume:
            if preset is not None or config_file is not None:
                raise ValueError("--resume reads the run's stored config; drop --preset and --config")
            run = overrides.get("run")
            if run is None:
                raise ValueError("--resume needs --run RUN_DIR (or --run-dir)")
            cfg = config_for_resume(Path(run), overrides)
        else:
            cfg = resolve_config(preset, config_file, overrides)
        result = train(cfg, resume=resume, show_progress=progress)
    except (ValueError, FileExistsError, FileNotFoundError) as exc:
        raise _fail(exc) from exc
    if result.validation:  # rank 0 of a distributed run, or a single process
        log.info("run %s: %d steps, %.1f min, validation %s", result.run_dir, result.step,
                 result.elapsed_seconds / 60, result.validation)


def _build_train_signature() -> inspect.Signature:
    params = [
        inspect.Parameter("preset", inspect.Parameter.KEYWORD_ONLY, annotation=str | None,
                          default=typer.Option(None, "--preset",
                                               help=f"Starting values: {', '.join(sorted(PRESETS))}.")),
        inspect.Parameter("config", inspect.Parameter.KEYWORD_ONLY, annotation=Path | None,
                          default=typer.Option(None, "--config", help="JSON file of config values.")),
        inspect.Parameter("resume", inspect.Parameter.KEYWORD_ONLY, annotation=bool,
                          default=typer.Option(False, "--resume",
                                               help="Continue the run in --run from its checkpoint.")),
        inspect.Parameter("progress", inspect.Parameter.KEYWORD_ONLY, annotation=bool,
                          default=typer.Option(True, "--progress/--no-progress",
                                               help="Show a progress bar.")),
    ]
    for name, annotation, help_text, aliases in _config_fields():
        flag = "--" + name.replace("_", "-")
        decls = [f"{flag}/--no-{name.replace('_', '-')}"] if annotation is bool else [flag, *aliases]
        option = typer.Option(None, *decls, help=help_text, show_default=False)
        params.append(inspect.Parameter(name, inspect.Parameter.KEYWORD_ONLY,
                                        annotation=_option_type(annotation), default=option))
    return inspect.Signature(params, return_annotation=None)


def export_command(
    run: Path = typer.Option(..., "--run", "--run-dir",
                             help="Run folder holding checkpoint.pt and split.json."),
    out: Path = typer.Option(Path("exported"), "--out", help="Artifact folder to write."),
    data: Path | None = typer.Option(None, "--data", help="Processed dataset (default: the run's)."),
    n_points: int | None = typer.Option(None, "--n-points",
                                        help="Points per query or part when serving (default: training N)."),
    placement_points: int | None = typer.Option(
        None, "--placement-points", min=1,
        help="Points h takes per query and part when serving (default: --n-points)."),
    catalog_points: int = typer.Option(256, "--catalog-points", help="Points stored per catalog part."),
    seed: int = typer.Option(0, "--seed", help="Seed of the catalog point samples."),
    duplicate_embedding_radius: float = typer.Option(0.05, "--duplicate-embedding-radius",
                                                     help="Near-duplicate: max embedding distance."),
    duplicate_chamfer_factor: float = typer.Option(
        0.65, "--duplicate-chamfer-factor",
        help="Near-duplicate: max Chamfer distance of the cached samples, in units of sqrt(area / samples)."),
    duplicate_size_tolerance: float = typer.Option(
        0.02, "--duplicate-size-tolerance",
        help="Near-duplicate: max relative difference of area and bounding-box extents."),
    max_megabytes: float = typer.Option(35.0, "--max-megabytes", help="Refuse to write a larger folder."),
    from_artifacts: Path | None = typer.Option(
        None, "--from-artifacts",
        help="Export the networks of this artifact folder instead of the run's checkpoint (the run then "
             "gives only the split and dataset): an exported model's catalog rebuilt over other data."),
) -> None:
    """Export a run: ONNX graphs, FAISS index, part catalog and manifest (service/artifacts/layout.py)."""
    from training.export import ExportOptions, export_run
    from training.from_onnx import trained_from_artifacts

    opts = ExportOptions(n_points=n_points, placement_points=placement_points, catalog_points=catalog_points,
                         seed=seed,
                         duplicate_embedding_radius=duplicate_embedding_radius,
                         duplicate_chamfer_factor=duplicate_chamfer_factor,
                         duplicate_size_tolerance=duplicate_size_tolerance, max_megabytes=max_megabytes)
    try:
        networks = trained_from_artifacts(from_artifacts) if from_artifacts is not None else None
        manifest = export_run(run, out, data=data, options=opts, networks=networks)
    except (ValueError, FileNotFoundError) as exc:
        raise _fail(exc) from exc
    log.info("wrote %s (model %s, %d parts)", out, manifest["model_version"], manifest["part_count"])


def familiarity_command(
    artifacts: Path = typer.Option(Path("exported"), "--artifacts",
                                   help="Exported folder to add the bank to."),
    per_shape: int = typer.Option(3, "--per-shape", min=1, help="Partial assemblies per training shape."),
    quantile: float = typer.Option(0.99, "--quantile", min=0.5, max=1.0,
                                   help="Threshold: this quantile of the bank's other-shape distances."),
    seed: int = typer.Option(0, "--seed", help="Seed of the partial assemblies."),
) -> None:
    """Add the familiarity check's bank (familiarity.npz) to an exported folder made before it.

    `complementme export` writes it; this gives an older export the same file and manifest entry
    without exporting its graphs or catalog again.
    """
    from training.export import ExportOptions, add_familiarity

    opts = ExportOptions(seed=seed, familiarity_per_shape=per_shape, familiarity_quantile=quantile)
    try:
        manifest = add_familiarity(artifacts, opts)
    except (ValueError, FileNotFoundError, RuntimeError) as exc:
        raise _fail(exc) from exc
    log.info("wrote %s/familiarity.npz: threshold %.3f over %d descriptors", artifacts,
             manifest["familiarity"]["threshold"], manifest["familiarity"]["queries"])


def category_head_command(
    artifacts: Path = typer.Option(Path("exported"), "--artifacts", help="Exported model to start from."),
    run: Path = typer.Option(..., "--run", "--run-dir",
                             help="The model's run folder: its split.json gives the training shapes."),
    outside: list[Path] = typer.Option(
        ..., "--outside",
        help="Processed outside collection whose category folders join the head's training (repeatable)."),
    out: Path = typer.Option(Path("exported"), "--out",
                             help="Artifact folder to write (may be --artifacts)."),
    data: Path | None = typer.Option(None, "--data",
                                     help="The model's processed dataset (default: the run's)."),
    queries: int = typer.Option(HeadFitSettings.queries, "--queries", min=64,
                                help="Partial assemblies the head is fitted on."),
    outside_share: float = typer.Option(HeadFitSettings.outside_share, "--outside-share", min=0.0, max=0.95,
                                        help="Share of the queries drawn from the outside collections."),
    seed: int = typer.Option(HeadFitSettings.seed, "--seed", help="Seed of the queries and the fit."),
) -> None:
    """Refit g's category head on the model's training shapes and outside collections; export.

    Every other weight stays as it is (training/category_head.py): retrieval and placement are
    unchanged, the category inferred for a request that names none is what changes.
    """
    import torch

    from training.category_head import refit_category_head
    from training.checkpoint import load_trained_config
    from training.data.processed import ProcessedDataset
    from training.export import export_run, options_of
    from training.from_onnx import trained_from_artifacts
    from training.split import load_split

    settings = HeadFitSettings(queries=queries, outside_share=outside_share, seed=seed)
    try:
        torch.manual_seed(seed)
        manifest = read_manifest(artifacts)
        trained, name = trained_from_artifacts(artifacts, suffix="head")
        own = ProcessedDataset.load(data if data is not None else Path(load_trained_config(run).data))
        split = load_split(run, own)
        others = {str(p): ProcessedDataset.load(p) for p in outside}
        report = refit_category_head(trained.pair.g, own.subset(split.train), others,
                                     list(manifest.get("categories", own.categories())), settings)
        trained.state["category_head"] = report
        written = export_run(run, out, data=data, options=options_of(manifest), networks=(trained, name))
    except (ValueError, FileNotFoundError, KeyError, ArtifactError) as exc:
        raise _fail(exc) from exc
    log.info("category head: %s", report)
    log.info("wrote %s (model %s)", out, written["model_version"])


def register_training_commands(app: typer.Typer) -> None:
    """Add `train`, `export`, `familiarity` and `category-head` to the root CLI."""
    signature = _build_train_signature()
    train_command.__signature__ = signature  # type: ignore[attr-defined]
    train_command.__annotations__ = {p.name: p.annotation for p in signature.parameters.values()}
    train_command.__annotations__["return"] = None
    app.command("train")(train_command)
    app.command("export")(export_command)
    app.command("familiarity")(familiarity_command)
    app.command("category-head")(category_head_command)
