"""`complementme data ...`: generate, ingest, preprocess and describe shape data.

Each command is a thin wrapper: parse options, call one function of the data package.
"""

from __future__ import annotations

from pathlib import Path

import typer

data_app = typer.Typer(help="Shape data: generate, ingest, preprocess (paper Section 4), statistics.",
                       no_args_is_help=True)

# Commands are added below, one function each: generate (generator), ingest, sweethome3d,
# flightgear, preprocess, stats.


# ---- generate ----------------------------------------------------------------------------------

@data_app.command("generate")
def generate_cmd(
    out: Path = typer.Option(Path("data/raw"), "--out", help="Writes <category>/<shape_id>.glb + .json."),
    seed: int = typer.Option(0, "--seed", min=0, help="Dataset seed (same seed: byte-identical files)."),
    shapes_per_category: int = typer.Option(180, "--shapes-per-category", min=1, help="Shapes per category."),
    category: list[str] | None = typer.Option(
        None, "--category", help="Only this category (repeat for several; default: all)."),
    workers: int = typer.Option(2, "--workers", min=1, help="Worker processes (the output does not change)."),
) -> None:
    """Generate the procedural part-structured shape dataset (categories, styles, labelled parts)."""
    from training.data.generator import CATEGORIES, generate_dataset

    unknown = [c for c in category or [] if c not in CATEGORIES]
    if unknown:
        raise typer.BadParameter(f"unknown category {', '.join(unknown)}; known: {', '.join(CATEGORIES)}",
                                 param_hint="--category")
    paths = generate_dataset(out, seed=seed, shapes_per_category=shapes_per_category, categories=category,
                             workers=workers)
    typer.echo(f"{out}: {len(paths)} shapes written")


# ---- ingest, preprocess, stats ---------------------------------------------------------------

@data_app.command("ingest")
def ingest_cmd(
    src: Path = typer.Argument(..., help="Folder of shape files: OBJ, GLB/GLTF, PLY, OFF, STL, .pts + .seg."),
    out: Path = typer.Option(Path("data/raw"), "--out", help="Raw dataset folder to write (GLB + sidecar)."),
    category: str | None = typer.Option(
        None, "--category", help="Category of every shape (default: the sidecar's, else the folder's)."),
    ignore_obj_materials: bool = typer.Option(
        False, "--ignore-obj-materials", help="Drop OBJ mtllib/usemtl lines instead of refusing the file."),
    max_vertices: int = typer.Option(2_000_000, help="Refuse meshes with more vertices."),
    max_faces: int = typer.Option(4_000_000, help="Refuse meshes with more triangles."),
) -> None:
    """Convert a folder of user meshes or segmented point clouds into the built-in raw format."""
    from training.data.ingest import IngestConfig, ingest_folder

    config = IngestConfig(ignore_obj_materials=ignore_obj_materials, max_vertices=max_vertices,
                          max_faces=max_faces)
    report = ingest_folder(src, out, category, config)
    typer.echo(report.table())
    if not report.written:
        raise typer.Exit(code=1)


@data_app.command("sweethome3d")
def sweethome3d_cmd(
    libraries: list[Path] = typer.Argument(..., help=(
        "Sweet Home 3D furniture libraries (.sh3f), or folders of them (Debian's sweethome3d-furniture: "
        "/usr/share/sweethome3d/furniture).")),
    out: Path = typer.Option(Path("data/real/src"), "--out",
                             help="Writes <category>/<model>.obj + sources.json."),
) -> None:
    """Chairs, tables, sofas and lamps of furniture libraries as OBJ files for `data ingest`."""
    from training.data.sweethome3d import LibraryError, export_library

    paths = sorted(p for lib in libraries for p in ([lib] if lib.is_file() else lib.glob("*.sh3f")))
    if not paths:
        typer.echo(f"error: no .sh3f library in {', '.join(map(str, libraries))} (install Debian's "
                   "sweethome3d-furniture, or name the files)", err=True)
        raise typer.Exit(2)
    try:
        counts = export_library(paths, out)
    except LibraryError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from exc
    filed = ", ".join(f"{n} {c}" for c, n in sorted(counts.items()))
    typer.echo(f"{out}: {filed} from {len(paths)} libraries")


@data_app.command("flightgear")
def flightgear_cmd(
    root: Path = typer.Argument(..., help=(
        "Folder of AC3D aircraft models (Debian's flightgear-data-ai: "
        "/usr/share/games/flightgear/AI/Aircraft).")),
    out: Path = typer.Option(Path("data/real-air/src"), "--out",
                             help="Writes airplane/<model>.obj + sources.json."),
    min_objects: int = typer.Option(3, "--min-objects", min=2, help="Skip models with fewer part objects."),
) -> None:
    """FlightGear's AI aircraft (AC3D) as OBJ files for `data ingest`, a group per object."""
    from training.data.flightgear import export_aircraft

    if not root.is_dir():
        typer.echo(f"error: {root} is not a folder (install Debian's flightgear-data-ai, or name one)",
                   err=True)
        raise typer.Exit(2)
    written, skipped = export_aircraft(root, out, min_objects)
    for reason in skipped:
        typer.echo(f"skipped {reason}", err=True)
    typer.echo(f"{out}: {written} airplanes, {len(skipped)} files unreadable")
    if not written:
        raise typer.Exit(1)


@data_app.command("preprocess")
def preprocess_cmd(
    raw: Path = typer.Option(Path("data/raw"), "--raw", help="Raw shapes (data generate / ingest)."),
    out: Path = typer.Option(Path("data/processed"), "--out", help="Processed dataset folder to write."),
    workers: int = typer.Option(2, "--workers", min=1, help="Worker processes (the output does not change)."),
    tau_proximity: float = typer.Option(0.05, help="Contact edge below this distance (fraction of radius)."),
    tau_size: float = typer.Option(0.2, help="Merge components whose PCA box diagonal is below this."),
    tau_hausdorff: float = typer.Option(0.05, help="Group components within this directional Hausdorff."),
    min_components: int = typer.Option(2, help="Discard shapes with fewer components after merging."),
    max_components: int = typer.Option(8, help="Discard shapes with more components after merging."),
    points_per_component: int = typer.Option(2048, help="Surface samples cached per component."),
    seed: int = typer.Option(0, help="Root seed of all sampling."),
) -> None:
    """Merge pieces into components and build contact graphs (paper Section 4)."""
    from training.data.preprocess import PreprocessConfig, preprocess_folder

    config = PreprocessConfig(tau_proximity=tau_proximity, tau_size=tau_size, tau_hausdorff=tau_hausdorff,
                              min_components=min_components, max_components=max_components,
                              points_per_component=points_per_component, seed=seed)
    ds = preprocess_folder(raw, out, config, workers=workers)
    counts = ds.info["counts"]
    typer.echo(f"{out}: {counts['kept']} shapes kept ({counts['components']} components), "
               f"{counts['rejected']} discarded; merges {ds.info['merge_counts']}")


@data_app.command("stats")
def stats_cmd(
    processed: Path = typer.Option(Path("data/processed"), "--processed", help="Processed dataset folder."),
    out: Path = typer.Option(Path("docs/data"), "--out", help="Where to write the PNG, table and JSON."),
) -> None:
    """Histograms of components per shape, merge counts and discarded shapes."""
    from training.data.stats import TABLE_TXT, write_stats

    if not (processed / "dataset.json").is_file():
        typer.echo(f"error: {processed} holds no processed dataset (dataset.json); make one with "
                   "`complementme data generate` and `complementme data preprocess`", err=True)
        raise typer.Exit(2)
    write_stats(processed, out)
    typer.echo((out / TABLE_TXT).read_text(), nl=False)
