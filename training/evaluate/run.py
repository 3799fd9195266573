"""The benchmark driver: load what ships, build the methods, run every table, write the results.

``run_benchmark`` is what ``complementme evaluate`` calls. It

1. loads the artifact folder with the service's own loader and builds the service's suggestion
   engine on it ("Ours" is evaluated through that engine);
2. draws the seeded queries of ``protocol`` from the catalog's held-out shapes;
3. builds the baselines (Random, CK10, and the fixed-embedding g, trained briefly on the
   training split of the processed dataset or loaded from its cache: ``--fixed-cache``, else the run
   folder);
4. evaluates Tables 1-4, the exact-component recall, the placement plausibility and Table 1 on
   perturbed queries (``robustness``);
5. writes ``results.json``, the Markdown report and the PNG charts (``report``).

Layout of ``results.json`` (undefined values are null)::

    benchmark_version, command, date (UTC, YYYY-MM-DD)
    artifact:  folder, model_version, format_version, created, part_count, n_points,
               dataset_hash, training (the manifest's training block)
    settings:  every BenchmarkSettings field (nested: retrieval, contact, fixed)
    categories: [category, ...]          methods: {name: description}   method_order: [name, ...]
    queries:   {all_but_one | single | placement_train | placement_test: {category: count}}
    pool:      {category: catalog parts of that category}
    tables:
      functional_map, hausdorff, hausdorff_one_component (removed labels of one component),
      hausdorff_right_label (the top 5's parts of the removed label only),
      style_map_all_but_one, style_map_single,
      recall@1, recall@10, median_percentile_rank, in_category_top5 (share of the top 5 from the
      query's category), missing_label_coverage_top10, distinct_labels_top10, live_modes (one-part
      queries with two or more labels missing):
                 {method: {category: value, ..., "mean": mean of categories, "n": {category: count}}}
      size_fit: {"placed-box IoU, fitting on" | ... off | ... "fitting on, contact-refined (as /place
                 answers)" | "scale error, fitting on" | ... off |
                 "placed-box IoU, fitting on, like with like" (top part of the removed label, one component):
                 {category: value, ...}} (the top suggestion of each all-but-one query, placed)
      placement_error, placement_error_refined (after contact refinement):
                        {"train" | "test": {category: value, ..., "mean": ..., "n": {...}}}
      plausibility:     {"top1" | "top1_refined" | "true_h" | "true_h_refined" | "true_gt":
                         {category | "all": {n, floating,
                         interpenetrating, median_gap, median_depth}}}
      robustness:       {"functional_map_category" | "functional_map_all" | "in_category_all":
                         {perturbation: {category: value, ..., "mean": ..., "n": {...}}}} (Ours on
                         the all-but-one queries perturbed, ``robustness.PERTURBATIONS``)
      robustness_likelihood: the same for "Ours (likelihood only)", when that method is run
      intervals:        {table key | size-fit row title: [low, high]} 95% bootstrap interval of
                        Ours' "mean" in that table (placement_error: the test split)
    fixed_embedding: steps, train_seconds, final_loss, pca_explained_variance, scale, cached, ...
    timing_seconds:  {stage: seconds, "total": seconds}

With ``details``, ``queries.json`` holds every query's record (top-5 part ids and metrics).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from service.artifacts.layout import MANIFEST, write_json_atomic
from service.artifacts.loading import load_artifacts
from service.settings import Settings
from service.suggest.engine import SuggestionEngine
from training.evaluate.baselines import CK10Method, Method, RandomMethod
from training.evaluate.evaluation import (
    ContactSettings,
    RetrievalSettings,
    evaluate_coverage,
    evaluate_placement,
    evaluate_plausibility,
    evaluate_retrieval,
    evaluate_size_fit,
    interval,
    median_table,
    plausibility_table,
    table,
)
from training.evaluate.fixed_embedding import FixedSettings
from training.evaluate.ours import EngineMethod
from training.evaluate.protocol import ShapeIndex, make_placement_queries, make_queries
from training.evaluate.robustness import PERTURBATIONS, POOLS, evaluate_robustness

log = logging.getLogger(__name__)

RESULTS_FILE = "results.json"
QUERIES_FILE = "queries.json"
BENCHMARK_VERSION = 1
METHOD_KEYS = ("random", "ck10", "fixed", "likelihood", "ranked", "ours")
# Table order, as in the paper: baselines first. "likelihood" is the paper's ranking: the mixture
# log-likelihood alone, without the complement check (service.suggest.complement) and in
# likelihood order. "ranked" is Ours in the service's other order (COMPLEMENTME_SUGGEST_ORDER=
# likelihood: no slots dealt to g's modes), which only differs from Ours for a model with several
# live modes.
METHOD_NAMES = {"random": "Random", "ck10": "CK10", "fixed": "Ours (fixed embedding)",
                "likelihood": "Ours (likelihood only)", "ranked": "Ours (likelihood order)", "ours": "Ours"}


@dataclass
class BenchmarkSettings:
    """Everything one benchmark run depends on (stored in results.json)."""

    artifacts: Path = Path("exported")
    run: Path | None = Path("runs/shipped")   # run folder: its split.json is checked; the
                                              # fixed-embedding cache lives here unless fixed_cache
    fixed_cache: Path | None = None           # folder of the fixed-embedding baseline's weights
                                              # (committed beside a report, every host reads the
                                              # same baseline: its training differs across hosts)
    database: str = "components"              # or "grouped": artifacts and data are the grouped ones
                                              # (training.evaluate.grouped), for the report to say
    data: Path | None = None                  # processed dataset (default: the manifest's path)
    out: Path = Path("docs/benchmark")        # results.json and the PNG charts
    report: Path = Path("docs/benchmark.md")
    seed: int = 0
    queries_per_category: int = 100           # per setting (all-but-one, single); paper: 100
    query_split: str = "test"                 # retrieval queries from these shapes ("train": for
                                              # choosing service settings without the held-out ones)
    placement_queries_per_category: int = 100  # per split (train, test)
    plausibility_queries_per_category: int = 50   # per category: all-but-one and test placement queries
                                              # whose placements get the (costly) contact test
    robustness: bool = True                   # Table 1 of Ours on perturbed queries (robustness.py)
    n_points: int | None = None               # query points (default: the artifacts' query_points)
    dense_points: int = 1024                  # surface samples per part (queries, Hausdorff, contact)
    methods: tuple[str, ...] = METHOD_KEYS
    ck10_shapes: int = 5                      # CK10: most similar shapes whose parts come first
    descriptor_pairs: int = 4096              # random pairs/triples per D2/A3 descriptor
    threads: int = 0                          # torch threads (0 = torch's default)
    details: bool = False                     # also write every query's record (queries.json)
    progress: bool = True
    command: str = ""                         # the command line, for the report
    notes: str | None = None                  # Markdown of the report's Analysis section
    retrieval: RetrievalSettings = field(default_factory=RetrievalSettings)
    contact: ContactSettings = field(default_factory=ContactSettings)
    fixed: FixedSettings = field(default_factory=FixedSettings)

    def validate(self) -> None:
        if self.database not in ("components", "grouped"):
            raise ValueError(f"database {self.database!r}: expected 'components' or 'grouped'")
        if self.query_split not in ("train", "test"):
            raise ValueError(f"query split {self.query_split!r}: expected 'train' or 'test'")
        unknown = [m for m in self.methods if m not in METHOD_KEYS]
        if unknown or not self.methods:
            raise ValueError(f"unknown method(s) {unknown}; choose among {', '.join(METHOD_KEYS)}")
        for name in ("queries_per_category", "placement_queries_per_category", "dense_points",
                     "ck10_shapes", "descriptor_pairs"):
            if getattr(self, name) <= 0:
                raise ValueError(f"benchmark setting {name} must be positive, got {getattr(self, name)}")
        if self.plausibility_queries_per_category < 0:
            raise ValueError("plausibility_queries_per_category must be >= 0")
        if self.retrieval.top_k <= 0 or any(k <= 0 for k in self.retrieval.recall_ks):
            raise ValueError("top_k and recall ks must be positive")
        if self.contact.tolerance <= 0 or self.contact.samples <= 0:
            raise ValueError("contact tolerance and samples must be positive")
        self.fixed.validate()


def quick_settings(base: BenchmarkSettings) -> BenchmarkSettings:
    """The CI variant: a few queries per category and a token fixed-embedding training."""
    return dataclasses.replace(
        base, queries_per_category=min(base.queries_per_category, 5),
        placement_queries_per_category=min(base.placement_queries_per_category, 5),
        plausibility_queries_per_category=min(base.plausibility_queries_per_category, 3),
        dense_points=min(base.dense_points, 512),
        fixed=dataclasses.replace(base.fixed, steps=min(base.fixed.steps, 50),
                                  minutes=min(base.fixed.minutes, 1.0)))


def settings_to_dict(s: BenchmarkSettings) -> dict[str, Any]:
    """Every setting but the notes, which results.json keeps once, at its top level."""
    d = dataclasses.asdict(s)
    d.pop("notes")
    return json.loads(json.dumps(d, default=str))


def _build_fixed(s: BenchmarkSettings, artifacts: Any, index: ShapeIndex) -> tuple[Method, dict[str, Any]]:
    """Load the processed dataset, take the catalog's training shapes, load or train g."""
    import torch

    from training.config import model_config_from_dict
    from training.data.processed import ProcessedDataset
    from training.evaluate.fixed_embedding import FixedEmbeddingMethod, load_or_train_fixed, rms_spread

    manifest = artifacts.manifest
    data = dataset_path(manifest, s.data, "the fixed-embedding baseline")
    cache = s.fixed_cache or s.run
    if cache is None:
        raise ValueError("the fixed-embedding baseline caches its weights in a folder: pass --fixed-cache "
                         "or --run")
    ds = ProcessedDataset.load(Path(data))
    want = manifest.get("dataset", {}).get("hash")
    have = ds.info.get("hash") or ds.content_hash()
    if want and want != have:
        raise ValueError(f"{data}: dataset hash {have[:12]} differs from the one the artifacts were exported "
                         f"from ({want[:12]}, {s.artifacts / 'manifest.json'})")
    train_ids = sorted(sid for sid in index.rows if index.split[sid] == "train")
    pos = {m["shape_id"]: i for i, m in enumerate(ds.shapes)}
    missing = [sid for sid in train_ids if sid not in pos]
    if missing:
        raise ValueError(f"{data}: {len(missing)} training shapes of the catalog are missing, "
                         f"e.g. {missing[0]!r}")
    train_shapes = [pos[sid] for sid in train_ids]
    train_ds = ds.subset(train_shapes)
    # Target descriptors of the training components: the very descriptors of their catalog parts
    # (part ids are "<shape_id>/<component index in the shape>"), so g trains on the same
    # coordinates it is evaluated with.
    rows = []
    for s_idx in train_shapes:
        sid = ds.shapes[s_idx]["shape_id"]
        n = int(ds.first_comp[s_idx + 1] - ds.first_comp[s_idx])
        if len(index.rows[sid]) != n:
            raise ValueError(f"{data}: shape {sid!r} has {n} components but {len(index.rows[sid])} "
                             "catalog parts")
        rows += [artifacts.catalog.lookup(f"{sid}/{j}") for j in range(n)]
    train_desc = index.part_descriptors(s.descriptor_pairs)[np.asarray(rows, np.int64)]
    if "model_config" not in manifest:
        raise ValueError(f"{s.artifacts / 'manifest.json'}: no model_config to rebuild g from")
    model_cfg = model_config_from_dict(manifest["model_config"])
    if s.threads:
        torch.set_num_threads(s.threads)
    # g trains as the shipped model did: its query size and batch, unless the caller set them.
    shipped = manifest.get("training", {})
    fixed_settings = dataclasses.replace(
        s.fixed, seed=s.seed, descriptor_pairs=s.descriptor_pairs,
        n_points=s.fixed.n_points or int(shipped.get("n_points") or artifacts.n_points),
        batch_size=s.fixed.batch_size or int(shipped.get("batch_size") or 32))
    model = load_or_train_fixed(cache, train_ds, train_desc, have, model_cfg, fixed_settings,
                                rms_spread(artifacts.catalog.embeddings))
    return FixedEmbeddingMethod(model, index.part_descriptors(s.descriptor_pairs)), model.info


def dataset_path(manifest: dict[str, Any], data: Path | None, what: str) -> Path:
    """The processed dataset: ``data``, else the one the artifacts' manifest was exported from."""
    path = data or Path(str(manifest.get("dataset", {}).get("path", "")))
    if not str(path):
        raise ValueError(f"{what} needs the processed dataset: pass --data")
    return Path(path)


def run_benchmark(s: BenchmarkSettings) -> dict[str, Any]:
    """Run the whole benchmark; write results.json, the report and the charts; return the results.

    With ``database`` "grouped" it runs on the artifacts' networks exported over the dataset
    grouped by label (``grouped.grouped_catalog``, kept under ``<run>/grouped``)."""
    s.validate()
    if s.database == "grouped":
        from training.evaluate.grouped import grouped_catalog

        if s.run is None:
            raise ValueError("the grouped database is kept in the run folder: pass --run")
        manifest = json.loads((Path(s.artifacts) / MANIFEST).read_text())
        data = dataset_path(manifest, s.data, "--database grouped")
        artifacts, data, run = grouped_catalog(s.artifacts, data, s.run / "grouped", s.seed)
        s = dataclasses.replace(s, artifacts=artifacts, data=data, run=run)
    return _Benchmark(s).run()


# The all-but-one tables of every method: (table key, per-query metric, median rather than mean).
_RETRIEVAL_METRICS = (("functional_map", "functional_ap", False),
                      ("hausdorff", "hausdorff", False),
                      ("hausdorff_one_component", "hausdorff_one_component", False),
                      ("hausdorff_right_label", "hausdorff_right_label", False),
                      ("style_map_all_but_one", "style_ap", False),
                      ("median_percentile_rank", "percentile", True),
                      ("in_category_top5", "in_category", False))


class _Benchmark:
    """One benchmark run: each method is one named step of ``run``, in the order they run.

    Every step that costs time records it in ``timing`` under the step's name.
    """

    def __init__(self, s: BenchmarkSettings) -> None:
        self.s = s
        self.t_all = time.monotonic()
        self.timing: dict[str, float] = {}
        self.tables: dict[str, Any] = {}
        self.per_query: dict[str, dict[str, list[dict[str, Any]]]] = {}
        self.placement: list[dict[str, Any]] = []
        self.coverage_records: dict[str, list[dict[str, Any]]] = {}   # per method
        self.size_fit_records: list[dict[str, Any]] = []               # Ours' top suggestions, placed
        self.plaus: dict[str, list[dict[str, Any]]] = {}

    @contextmanager
    def _timed(self, name: str) -> Iterator[None]:
        t = time.monotonic()
        yield
        self.timing[name] = round(time.monotonic() - t, 2)

    def run(self) -> dict[str, Any]:
        self.load()
        _check_split(self.s.run, self.index)
        self.draw_queries()
        self.build_methods()
        self.retrieval_tables()
        self.coverage_tables()
        if "ours" in self.s.methods:
            self.placement_tables()
            self.size_fit_table()
            self.plausibility_tables()
            if self.s.robustness:
                self.robustness_tables()
        self.interval_table()
        return self.write(self.results())

    def load(self) -> None:
        """The artifact folder through the service's loader, and the service's engine on it."""
        s = self.s
        with self._timed("load"):
            self.artifacts = load_artifacts(Path(s.artifacts))
            # The service's defaults, as shipped (only the artifact folder differs).
            self.service_settings = Settings().model_copy(update={"artifacts": Path(s.artifacts)})
            self.engine = SuggestionEngine(self.artifacts, self.service_settings)
            self.index = ShapeIndex(self.artifacts.catalog, dense_points=s.dense_points, seed=s.seed)
            # Enough points for every network (h may take more than f and g: placement_points).
            self.n_points = s.n_points or self.artifacts.query_points

    def draw_queries(self) -> None:
        """The seeded retrieval and placement queries of every category."""
        s, index, n = self.s, self.index, self.n_points
        with self._timed("queries"):
            self.cats = index.categories()
            self.queries = {setting: make_queries(index, setting, s.queries_per_category, n, s.seed,
                                                      split=s.query_split)
                            for setting in ("all_but_one", "single")}
            self.placement_queries = {
                split: make_placement_queries(index, split, s.placement_queries_per_category, n, s.seed)
                for split in ("train", "test")}
        if not self.queries["all_but_one"]:
            raise ValueError(f"{s.artifacts}: no held-out shape with two or more labelled parts: "
                             "nothing to evaluate")

    def build_methods(self) -> None:
        """Every method asked for, under its table name, with its description."""
        self.ours = EngineMethod(self.engine)
        self.methods: dict[str, Method] = {}
        self.descriptions: dict[str, str] = {}
        self.fixed_info: dict[str, Any] | None = None
        for key in self.s.methods:
            with self._timed(f"build {key}"):
                m = self._build_method(key)
                self.methods[METHOD_NAMES[key]] = m
                self.descriptions[METHOD_NAMES[key]] = str(getattr(m, "description", ""))

    def _build_method(self, key: str) -> Method:
        s = self.s
        if key == "random":
            return RandomMethod(len(self.artifacts.catalog), s.seed)
        if key == "ck10":
            return CK10Method(self.index, n_shapes=s.ck10_shapes, n_points=self.n_points, seed=s.seed,
                              n_pairs=s.descriptor_pairs)
        if key == "fixed":
            m, self.fixed_info = _build_fixed(s, self.artifacts, self.index)
            return m
        if key == "likelihood":
            return EngineMethod(SuggestionEngine(self.artifacts, self.service_settings.model_copy(
                update={"suggest_complement_check": False, "suggest_order": "likelihood",
                        "rank_scale_weight": 0.0, "rank_move_weight": 0.0})),
                name=METHOD_NAMES[key])
        if key == "ranked":
            return EngineMethod(SuggestionEngine(self.artifacts, self.service_settings.model_copy(
                update={"suggest_order": "likelihood"})), name=METHOD_NAMES[key])
        return self.ours

    def retrieval_tables(self) -> None:
        """Tables 1-3, exact-component recall and percentile rank, for every method."""
        s, cats = self.s, self.cats
        for name, m in self.methods.items():
            with self._timed(f"retrieval {name}"):
                self.per_query[name] = {
                    setting: evaluate_retrieval(m, qs, self.index, s.retrieval, s.progress)
                    for setting, qs in self.queries.items()}
        recall = [f"recall@{k}" for k in s.retrieval.recall_ks]
        for key in (*(k for k, _, _ in _RETRIEVAL_METRICS), "style_map_single", *recall):
            self.tables[key] = {}
        for name in self.methods:
            abo, single = self.per_query[name]["all_but_one"], self.per_query[name]["single"]
            for key, metric, median in _RETRIEVAL_METRICS:
                self.tables[key][name] = (median_table if median else table)(abo, metric, cats)
            self.tables["style_map_single"][name] = table(single, "style_ap", cats)
            for key in recall:
                self.tables[key][name] = table(abo, key, cats)

    def coverage_tables(self) -> None:
        """One part present, at least two labels missing: what the top 10 offer (model v3's aim)."""
        cats, tables = self.cats, self.tables
        for name, m in self.methods.items():
            with self._timed(f"coverage {name}"):
                coverage = evaluate_coverage(m, self.queries["single"], self.index, self.s.retrieval,
                                             progress=self.s.progress)
            self.coverage_records[name] = coverage
            tables.setdefault("missing_label_coverage_top10", {})[name] = table(coverage, "coverage", cats)
            tables.setdefault("distinct_labels_top10", {})[name] = table(coverage, "distinct_labels", cats)
            if any("live_modes" in r for r in coverage):
                tables.setdefault("live_modes", {})[name] = table(coverage, "live_modes", cats)

    def placement_tables(self) -> None:
        """Table 4: h's placement error on train and test shapes, before and after contact refinement."""
        with self._timed("placement"):
            for split in ("train", "test"):
                self.placement += evaluate_placement(self.ours, self.placement_queries[split],
                                                     self.s.progress)
            for key, metric in (("placement_error", "error"), ("placement_error_refined", "error_refined")):
                self.tables[key] = {
                    sp: table([r for r in self.placement if r["split"] == sp], metric, self.cats)
                    for sp in ("train", "test")}

    def size_fit_table(self) -> None:
        """The top suggestion of each all-but-one query, placed, against the removed part's box."""
        from training.evaluate.report import SIZE_FIT_ROWS  # the report (and matplotlib) only when run

        with self._timed("size fit"):
            fits = evaluate_size_fit(self.ours, self.queries["all_but_one"],
                                     self.per_query["Ours"]["all_but_one"], self.index, self.s.progress)
            self.tables["size_fit"] = {title: table(fits, key, self.cats) for title, key in SIZE_FIT_ROWS}
            self.size_fit_records = fits

    def plausibility_tables(self) -> None:
        """The contact test of the first all-but-one and test placement queries of each category."""
        s, n = self.s, self.s.plausibility_queries_per_category
        with self._timed("plausibility"):
            chosen = _first_per_category(self.queries["all_but_one"], n)
            test_pq = _first_per_category(self.placement_queries["test"], n)
            test_ids = {q.qid for q in test_pq}
            self.plaus = evaluate_plausibility(
                self.ours, self.index, chosen, self.per_query["Ours"]["all_but_one"],
                [r for r in self.placement if r["qid"] in test_ids], test_pq, s.contact, s.progress)
            self.tables["plausibility"] = {case: plausibility_table(recs, self.cats)
                                           for case, recs in self.plaus.items()}
            log.debug("plausibility on %d queries", len(chosen))

    def robustness_tables(self) -> None:
        """Table 1 of Ours on the all-but-one queries perturbed, with and without the category; and
        of "Ours (likelihood only)" when it is run: g's own robustness, without the service's
        fit key and order, which can hide a loss of g's (``robustness_likelihood``)."""
        like = METHOD_NAMES["likelihood"]
        for key, method in (("robustness", self.ours),
                            ("robustness_likelihood", self.methods.get(like))):
            if method is None:
                continue
            with self._timed(f"robustness {method.name}"):
                recs = evaluate_robustness(method, self.queries["all_but_one"], self.index, self.s.retrieval,
                                           self.s.seed, self.s.progress)
            self.tables[key] = _robustness_tables(recs, self.cats)

    def interval_table(self) -> None:
        """95% bootstrap intervals of Ours' headline means (queries resampled within their
        category, seeded): how far each figure would move with other queries of the same split."""
        ours, cats, seed = METHOD_NAMES["ours"], self.cats, self.s.seed
        if ours not in self.per_query:
            return
        sources: list[tuple[str, list[dict[str, Any]], str]] = [
            ("functional_map", self.per_query[ours]["all_but_one"], "functional_ap"),
            ("hausdorff", self.per_query[ours]["all_but_one"], "hausdorff"),
            ("style_map_all_but_one", self.per_query[ours]["all_but_one"], "style_ap"),
            ("missing_label_coverage_top10", self.coverage_records.get(ours, []), "coverage"),
            ("distinct_labels_top10", self.coverage_records.get(ours, []), "distinct_labels"),
            ("live_modes", self.coverage_records.get(ours, []), "live_modes"),
            ("placed-box IoU, fitting on", self.size_fit_records, "iou_on"),
            ("placement_error", [r for r in self.placement if r["split"] == "test"], "error")]
        self.tables["intervals"] = {key: interval(recs, metric, cats, seed)
                                    for key, recs, metric in sources if recs}

    def results(self) -> dict[str, Any]:
        """The results dict of ``results.json`` (layout in the module docstring)."""
        s, cats, catalog, manifest = self.s, self.cats, self.artifacts.catalog, self.artifacts.manifest
        results: dict[str, Any] = {
            "benchmark_version": BENCHMARK_VERSION,
            "command": s.command,
            "date": datetime.now(timezone.utc).strftime("%Y-%m-%d"),
            "artifact": {"folder": str(s.artifacts), "model_version": manifest["model_version"],
                         "format_version": manifest["format_version"], "created": manifest.get("created"),
                         "part_count": manifest["part_count"], "n_points": manifest["n_points"],
                         "placement_points": self.artifacts.placement_points,
                         "dataset_hash": manifest.get("dataset", {}).get("hash"),
                         "training": manifest.get("training", {})},
            "settings": settings_to_dict(s),
            "categories": cats,
            "methods": self.descriptions,
            "method_order": list(self.methods),
            "queries": {
                **{setting: _count(qs, cats) for setting, qs in self.queries.items()},
                **{f"placement_{split}": _count(qs, cats) for split, qs in self.placement_queries.items()},
            },
            "pool": {c: int(np.sum(catalog.category_of == catalog.categories.index(c))) for c in cats},
            "tables": self.tables,
            "fixed_embedding": self.fixed_info,
            "notes": s.notes,
            # The service's contact refinement, as the "contact-refined" rows ran it.
            "service_contact": {"contact_max_offset": self.engine.config.contact_max_offset,
                                "contact_tolerance": self.engine.config.contact_tolerance},
        }
        self.timing["total"] = round(time.monotonic() - self.t_all, 2)
        results["timing_seconds"] = self.timing
        return json_clean(results)

    def write(self, results: dict[str, Any]) -> dict[str, Any]:
        """results.json (and queries.json with ``details``), the report and the charts."""
        from training.evaluate.report import write_report

        s, out = self.s, Path(self.s.out)
        out.mkdir(parents=True, exist_ok=True)
        write_json_atomic(out / RESULTS_FILE, results)
        if s.details:
            write_json_atomic(out / QUERIES_FILE, json_clean({"retrieval": self.per_query,
                                                              "placement": self.placement,
                                                              "plausibility": self.plaus}))
        write_report(results, Path(s.report), out)
        log.info("benchmark done in %.1f s: %s, %s", self.timing["total"], out / RESULTS_FILE, s.report)
        return results


def rerender(out: Path, report: Path, notes: str | None = None, notes_file: Path | None = None) -> None:
    """Write the report and charts again from ``out/results.json``; ``notes`` (if given) replace its
    notes, and are saved back into the results file with ``--notes notes_file`` added to the
    recorded command (which then reproduces the report in one run)."""
    from training.evaluate.report import write_report

    path = Path(out) / RESULTS_FILE
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no results to render (run the benchmark first)")
    results = json.loads(path.read_text())
    if notes is not None:
        results["notes"] = notes
        command = str(results.get("command") or "")
        if notes_file is not None and command and "--notes" not in command.split():
            results["command"] = f"{command} --notes {notes_file}"
        write_json_atomic(path, results)
    write_report(results, Path(report), Path(out))


def _check_split(run: Path | None, index: ShapeIndex) -> None:
    """The catalog's ``split`` fields decide the held-out shapes; if the run folder holds the
    trainer's ``split.json``, it must agree (a catalog exported from another run would not)."""
    path = Path(run) / "split.json" if run is not None else None
    if path is None or not path.is_file():
        return
    try:
        want = set(json.loads(path.read_text())["test_ids"])
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"{path}: not a readable split file ({exc})") from exc
    have = {sid for sid, split in index.split.items() if split == "test"}
    if want != have:
        raise ValueError(f"{path}: its {len(want)} test shapes differ from the catalog's {len(have)} "
                         f"(e.g. {sorted(want ^ have)[:3]}); pass the run the artifacts were exported from")


def json_clean(obj: Any) -> Any:
    """The results with NaN (an undefined mean) as None, so results.json is strict JSON."""
    if isinstance(obj, dict):
        return {k: json_clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_clean(v) for v in obj]
    if isinstance(obj, float) and math.isnan(obj):
        return None
    return obj


def _count(queries: list[Any], categories: list[str]) -> dict[str, int]:
    return {c: sum(q.category == c for q in queries) for c in categories}


def _first_per_category(queries: list[Any], n: int) -> list[Any]:
    """The first ``n`` queries of each category (queries are already in seeded random order)."""
    seen: dict[str, int] = {}
    out = []
    for q in queries:
        if seen.get(q.category, 0) < n:
            out.append(q)
            seen[q.category] = seen.get(q.category, 0) + 1
    return out


def _robustness_tables(recs: list[dict[str, Any]], cats: list[str]) -> dict[str, Any]:
    """``evaluate_robustness``'s records as the results' robustness tables (layout above)."""
    def rows(key: str, scope: str) -> dict[str, Any]:
        return {name: table([r for r in recs if r["perturbation"] == name and r["pool"] == scope], key, cats)
                for name, _, _ in PERTURBATIONS}

    return {**{f"functional_map_{scope}": rows("functional_ap", scope) for scope in POOLS},
            "in_category_all": rows("in_category", "all")}
