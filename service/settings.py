"""Settings of the suggestion service, read from ``COMPLEMENTME_*`` environment variables.

One class holds every knob and every limit of the running server, so the README's table of
settings can be generated from it (``python -m service.settings > docs/settings.md``; a test
checks the file is up to date). Read settings through ``get_settings()``, never at import:
tests clear its cache to change them.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Literal

from pydantic import Field, SecretStr, field_validator, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from service.errors import InputError

ENV_PREFIX = "COMPLEMENTME_"

# The shipped artifacts live at the repository root, next to the `service` package.
DEFAULT_ARTIFACTS = Path(__file__).resolve().parent.parent / "exported"


class Settings(BaseSettings):
    """Every setting of the service; each field's description is its documentation."""

    # Errors name the setting and the problem but never echo its value: a too-short API key was
    # printed in the start-up error (and so in logs).
    model_config = SettingsConfigDict(env_prefix=ENV_PREFIX, extra="ignore", hide_input_in_errors=True)

    # --- where and how to serve -------------------------------------------------------------
    artifacts: Path = Field(default=DEFAULT_ARTIFACTS, description=(
        "Folder of exported artifacts (manifest.json, ONNX graphs, FAISS index, catalog)."))
    host: str = Field(default="127.0.0.1", description="Address `complementme serve` binds to.")
    port: int = Field(default=8000, ge=0, le=65535, description=(
        "Port `complementme serve` listens on (0: any free port)."))
    log_level: Literal["debug", "info", "warning", "error"] = Field(
        default="info", description="Log level of the server.")
    verify_checksums: bool = Field(default=True, description=(
        "Check every artifact file against its SHA-256 in manifest.json at start."))

    # --- compute ----------------------------------------------------------------------------
    onnx_threads: int = Field(default=1, ge=1, le=64, description=(
        "Intra-op threads of each ONNX Runtime session (spinning is always off, so idle "
        "threads do not starve FAISS)."))
    faiss_threads: int = Field(default=1, ge=1, le=64, description="OpenMP threads FAISS searches with.")
    blas_threads: int = Field(default=1, ge=1, le=64, description=(
        "Threads numpy's BLAS may use (the brute-force search's matrix products). Its default of "
        "one per core made two server processes fight over both cores and halved their throughput."))
    faiss_blas_threshold: int = Field(default=20, ge=1, description=(
        "Batches of at least this many queries take FAISS's BLAS path (faster for batched "
        "searches; FAISS's own default of 128000 never takes it)."))
    max_points_per_run: int = Field(default=1024, ge=1, description=(
        "Most points (queries x points per query) in one ONNX Runtime run; larger batches are "
        "split (always at least one query per run). Per-point activations of a big run leave the "
        "CPU caches: a paper-size PointNet took about 3 ms per 1000-point query alone and 6 ms "
        "per query in runs of four."))
    batch_max_size: int = Field(default=32, ge=1, le=1024, description=(
        "Most queries the micro-batcher runs in one engine call: concurrent `/suggest`, "
        "`/suggest/mesh` and `/suggest/batch` queries queue and run together (one `/suggest/batch` "
        "request larger than this runs alone)."))
    batch_max_wait_ms: float = Field(default=2.0, ge=0, le=1000, description=(
        "Longest time, in milliseconds after the oldest queued query, that the micro-batcher waits "
        "for requests still being read or parsed before it runs a partial batch. A lone request "
        "never waits: with nothing on the way the batch runs at once."))
    batch_max_cost_ms: float = Field(default=200.0, gt=0, description=(
        "Most estimated CPU milliseconds of queries the micro-batcher runs in one engine call "
        "(the estimate of `max_request_cost_ms`; a single query over it runs alone). A request "
        "whose queries do not fit runs in several calls, and between them the queries of other "
        "requests go first: a large `/suggest/batch` delays a concurrent `/suggest` by about one "
        "call, not by its whole run."))
    overlap_max_batch: int = Field(default=2, ge=0, le=1024, description=(
        "Engine calls of at most this many queries run the placement network's query branch "
        "(h_query) on a second thread while g, the search and the scoring run: a lone request "
        "finishes about a tenth sooner over HTTP when a core is free. Larger batches mean a loaded "
        "server, where no core is free and the extra thread only contended (0: never)."))
    batch_workers: int = Field(default=1, ge=1, le=16, description=(
        "Threads that run the micro-batcher's engine calls (the only threads calling ONNX Runtime "
        "and FAISS for suggestions, so they do not contend)."))
    neighbours_per_mode: int = Field(default=64, ge=1, le=4096, description=(
        "Catalog parts FAISS returns for each mixture mean (at least the request's k); their "
        "union is re-scored by the exact mixture log-likelihood."))
    brute_force_max_parts: int = Field(default=50_000, ge=0, description=(
        "A catalog with a flat (exact) index and at most this many parts is searched by numpy "
        "brute force instead of FAISS: the same parts, 3-4x faster at the shipped size, where "
        "FAISS's per-row heaps cost more than the distances. 0: always FAISS."))
    exact_search_max_filtered: int = Field(default=20_000, ge=0, description=(
        "A filtered query whose filter (categories, styles, exclusions) leaves at most this many "
        "parts searches them exactly: with an approximate index (IVF or HNSW, chosen for large "
        "catalogs) always, since its probes may hold few of them; with a flat index when they are "
        "under half the catalog, since that beats a selector scan of every part."))
    gc_threshold: int = Field(default=50_000, ge=100, description=(
        "Allocations between the garbage collector's youngest-generation passes (Python's "
        "default: 700). A JSON request holds about 1000 lists of coordinates until it is "
        "answered, so at 700 the collector ran more than once per request and walked the lists "
        "of every request in flight: concurrency 32, JSON bodies, two server processes: 345-379 req/s at "
        "700, 470-523 at 50,000."))
    seed: int = Field(default=0, description=(
        "Seed of the deterministic resampling of inputs to the model's point count and of "
        "mesh surface sampling."))
    warmup: bool = Field(default=True, description=(
        "Run one suggestion at start, load the compiled kernels and make what `/assemble` reads "
        "of each category's training shapes and build every route's request models (about 0.5 s "
        "in all), so that no first request pays for them; `/readyz` reports ready only "
        "after it passed."))

    # --- modeling: contact refinement, preferences, assembly, export (docs/modeling.md) -------
    contact_max_offset: float = Field(default=0.1, ge=0, le=1, description=(
        "Largest move of contact refinement, in units of the complete object's radius; a part "
        "that needs more keeps the placement network's translation (0: refinement never moves)."))
    contact_tolerance: float = Field(default=0.01, gt=0, le=0.1, description=(
        "Gap and penetration depth (sampled, object radius units) that count as touching; also "
        "the step of the refinement's line search."))
    contact_reach: float = Field(default=0.25, ge=0, le=1, description=(
        "A placed part that contact refinement cannot bring into contact within "
        "`contact_max_offset` and that floats (apart from the assembly, not sunk into it) gets a "
        "second search reaching this far (object radius units): h sometimes leaves a part hanging "
        "in the air (`/place`, `/assemble`, refined suggestions). At most `contact_max_offset`: off."))
    suggest_refine_contact: bool = Field(default=False, description=(
        "Contact refinement of suggestions (`/suggest`, `/suggest/mesh`, `/suggest/batch`) when a "
        "request does not send `refine_contact`. Off by default: for k = 10 it adds about 2.5 ms "
        "of CPU to a suggestion of about 2.5-3 (2.1 ms of wall time on two threads, "
        "`contact_threads`), which would cost the service about half its throughput and its c = 1 "
        "latency target "
        "(docs/performance.md); `/place` and `/assemble` refine unless told not to."))
    suggest_complement_check: bool = Field(default=True, description=(
        "Complement check of suggestions when a request does not send `complement_check`: the "
        "best-ranked candidates are placed by the placement network and those lying mostly on the "
        "query's own surface (parts the query already has) move behind the others."))
    complement_candidates: int = Field(default=128, ge=1, le=1000, description=(
        "Best-ranked candidates (after duplicate collapse) the placement network places before the "
        "answer is ordered (the complement check tests them, the fit key re-sorts them, the share "
        "order deals them); at least the request's k. 128 rather than 64 since the fit key: on "
        "the training split it took the coverage of the missing labels from 0.903 to 0.908 (96: "
        "0.905, 256: 0.922, at lower functional mAP@5 and a larger Hausdorff distance). It was 96 "
        "until h's head was split between its branches (2026-12-05): 128 then took the engine's "
        "p50 past issue 6's 3 ms; now 2.34 ms (96: 2.25 ms; `python -m bench engine`)."))
    complement_part_samples: int = Field(default=16, ge=1, le=4096, description=(
        "Catalog point samples per candidate the complement check measures (at most the "
        "catalog's points per part)."))
    complement_cover_distance: float = Field(default=0.08, gt=0, le=1, description=(
        "A placed candidate's sample is on the query's surface when a query point lies within "
        "this distance (object radius units)."))
    complement_cover_share: float = Field(default=0.5, gt=0, le=1, description=(
        "Candidates with at least this share of their samples on the query's surface count as "
        "already present and are demoted."))
    region_candidates: int = Field(default=256, ge=1, le=4096, description=(
        "The candidate budget of a suggestion request with a `region` (\"suggest for this "
        "spot\"): this many best-ranked candidates (after duplicate collapse; at least the "
        "request's k) are placed by the placement network, and the k suggestions are the best of "
        "those whose placed box reaches into the region. FAISS returns at least this many parts "
        "per mixture mean for such a request. A part ranked below the budget is never offered "
        "for the spot; the answer's `region` says how many were placed and how many fell in."))
    contact_search_points: int = Field(default=128, ge=8, le=4096, description=(
        "Samples per side (part, assembly) measured at each candidate offset of the refinement."))
    contact_part_samples: int = Field(default=512, ge=32, le=20_000, description=(
        "Oriented surface samples drawn from each catalog part's mesh for contact tests (cached)."))
    contact_assembly_points: int = Field(default=20_000, ge=16, description=(
        "Most query points used as the assembly in contact tests (more are subsampled, seeded)."))
    contact_cache_parts: int = Field(default=4096, ge=1, description=(
        "Catalog parts whose contact samples are kept in memory (least recently used dropped)."))
    contact_threads: int = Field(default=2, ge=1, le=64, description=(
        "Threads one refinement spreads its parts over (each part's search is independent, so "
        "the answers do not depend on it). 2, the cores of the machines it was measured on, took "
        "the benchmark query's k = 10 refinement from 3.9 to 2.3 ms (its parts at their fitted "
        "size, on the Intel host of docs/performance.md's section e); a server already busy on "
        "every core gains nothing from more than 1 (docs/performance.md)."))
    suggest_order: Literal["share", "likelihood"] = Field(default="share", description=(
        "Order of suggestions. `share` (the default): the first `share_order_head` slots in "
        "mixture-likelihood order, the rest dealt to g's modes in proportion to their weights "
        "(Sainte-Lague's highest averages), each mode giving its own best parts: the paper's sampling "
        "from the mixture, made deterministic, so after its surest parts a seat alone also gets "
        "legs and arms in the shares g gives them. `likelihood`: by mixture likelihood alone, "
        "where the mode whose parts lie closest to its mean takes every slot. Measured on the "
        "shipped model (docs/benchmark.md, `Ours` and `Ours (likelihood order)`): for a single "
        "part the top 10 hold 2.3 kinds of part and 67% of the missing labels against 1.25 and "
        "42%, at a functional mAP@5 of 0.788 against 0.793. A request's `diversity` still asks "
        "for the round-robin gallery; a request's `region` keeps the likelihood order (the spot "
        "already says what kind of part is wanted)."))
    share_min_mode_weight: float = Field(default=0.05, ge=0, le=1, description=(
        "In the `share` order, modes lighter than this get slots only after the others ran out."))
    share_order_head: int = Field(default=5, ge=0, description=(
        "In the `share` order, the first this many slots keep the likelihood order (the model's "
        "surest parts first); the slots after them are dealt to the modes, counting the first "
        "ones as their modes' slots. 0 deals every slot (functional mAP@5 0.649 against 0.788 "
        "with 5, the same coverage of the missing labels)."))
    share_spread_sigmas: float = Field(default=1.5, ge=0, description=(
        "In the `share` order, a part after the first `share_order_head` slots that lies within "
        "this many of its mode's standard deviations (RMS over the embedding's dimensions) of a "
        "part shown before it waits until the other parts have filled the k slots: to g the two "
        "are one suggestion, and a near-copy of a back already shown hides an arm. 0 turns it "
        "off. Chosen on the training split's single-part queries for the shipped model, whose "
        "sigmas are sharper than its predecessor's (about 0.049 against 0.060): coverage of the "
        "missing labels 0.869 / 0.894 / 0.906 / 0.889 / 0.863 at 1 / 1.25 / 1.5 / 1.75 / 2. "
        "The head, and so functional mAP@5, is unchanged (docs/benchmark.md has the held-out "
        "figures)."))
    rank_scale_weight: float = Field(default=50.0, ge=0, description=(
        "The answer order ranks by the mixture log-likelihood less this times the mean absolute "
        "log of the part's fitted scale (the placement network's per-axis scale, clipped to "
        "`scale_min`..`scale_max`): among parts g rates alike, the one that fits without "
        "rescaling comes first (service.suggest.fit_rank). 0 turns it off. The answer's `score` "
        "stays the log-likelihood. Chosen with `rank_move_weight` on the training split's "
        "all-but-one queries (docs/training.md)."))
    rank_move_weight: float = Field(default=25.0, ge=0, description=(
        "The answer order also subtracts this times the distance (object radius units) between "
        "where the placement network puts a part and where it sat in its own shape: a part that "
        "fills the same spot in its source shape is preferred. 0 turns it off."))
    infer_category: bool = Field(default=True, description=(
        "When a suggestion request names no category and the model has a category head, infer "
        "the category from the partial assembly, report it (`inferred_category`) and keep the "
        "suggestions in it when the inference is sure enough."))
    category_min_confidence: float = Field(default=0.5, ge=0, le=1, description=(
        "Inferred-category probability from which suggestions are kept in that category; below "
        "it the answer is unfiltered and carries a `category_unsure` warning."))
    fit_scale: bool = Field(default=True, description=(
        "Fit suggested and placed parts in size (per-axis scale from the placement network's "
        "scale head) when a request does not send `fit_scale`. The catalog geometry never changes."))
    scale_min: float = Field(default=0.5, gt=0, le=1, description=(
        "Smallest fitted scale per axis (larger shrinkage is clipped)."))
    scale_max: float = Field(default=2.0, ge=1, le=10, description=(
        "Largest fitted scale per axis (larger growth is clipped)."))
    fit_frame_uploads: bool = Field(default=True, description=(
        "A mesh upload (`/suggest/mesh`, `/assemble/mesh`) sent without `frame` gets the complete "
        "object's frame estimated from the partial one (`fit_frame`); JSON points without `frame` "
        "are taken as canonical unless the request asks `fit_frame: true`."))
    fit_frame_max_ratio: float = Field(default=2.5, ge=1, le=10, description=(
        "Frame fitting tries complete objects up to this many times the partial's own radius."))
    fit_frame_ratios: int = Field(default=5, ge=1, le=20, description=(
        "Radii frame fitting tries, from the partial's own radius to `fit_frame_max_ratio` times it "
        "(evenly spaced in log scale)."))
    fit_frame_radius_prior: float = Field(default=0.8, ge=0, le=10, description=(
        "Frame fitting keeps the hypothesis of the smallest familiarity distance plus this many "
        "times the log of its radius over the partial's own: without it, a partial at the bottom "
        "of a room much larger than the object could look as familiar as the right frame."))
    fit_frame_category_weight: float = Field(default=16.0, ge=0, le=100, description=(
        "Frame fitting adds this many times the log of the category head's probability of the "
        "query's category (the named one, else the most probable) to each hypothesis's score: a "
        "real object's frame is the one in which it looks like its kind (0: familiarity and the "
        "radius prior alone)."))
    fit_frame_shifts: int = Field(default=9, ge=1, le=21, description=(
        "Positions along the up axis frame fitting tries for the partial inside the complete "
        "object's room (from the bottom to the top); with each up axis and radius one query of a "
        "single batch (2 x 5 x 9 = 90 by default, fewer where they coincide)."))
    ood_max_extent: float = Field(default=2.5, gt=1, description=(
        "A query whose points reach further than this from their box centre in the model's frame "
        "(unit radius; a whole object reaches 1) is far outside what the model knows: the answer "
        "carries a `frame` warning (set `frame.radius` and `frame.center`)."))
    ood_min_extent: float = Field(default=0.1, gt=0, lt=1, description=(
        "A query smaller than this in the model's frame gets the same `frame` warning (one small "
        "part, a trigger or a bulb, reaches about 0.1)."))
    ood_max_mode_distance: float = Field(default=1.2, gt=0, description=(
        "A query whose ranked candidates all lie further than this from their modes' means, in "
        "those modes' sigmas (root mean square over the embedding's dimensions), gets an `unfamiliar` "
        "warning: nothing in the catalog is like what the model expects to complement it. "
        "Measured with the shipped model on 120 held-out all-but-one queries (the closest of the "
        "shortlist): at most 1.0 (p99 0.9); the same queries twice too large without a frame: "
        "median 1.2, at most 2.0; four times: median 4.3, at least 1.0 (each of those also gets "
        "`frame` or `unfamiliar_shape`). Shapes of no known category (a ball, a torus, a cube, a plate, a "
        "helix, noise) score 0.72-0.96, like known ones: this warning catches frames off in "
        "size, not unknown categories (`familiarity_check` does)."))
    familiarity_check: bool = Field(default=True, description=(
        "Compare g's answer for a query (its mixture means and log weights) with g's answers for "
        "training partial assemblies shipped with the model (`familiarity.npz`); a query whose "
        "nearest one lies further than the threshold gets an `unfamiliar_shape` warning: the "
        "partial assembly is unlike any shape the model was trained on (of no known category), "
        "so the inferred category and the suggestions are guesses. Artifacts exported without "
        "the bank are not checked."))
    familiarity_threshold: float | None = Field(default=None, gt=0, description=(
        "The distance past which `familiarity_check` warns; unset: the threshold calibrated at "
        "export (the 0.99 quantile of the training bank's distances to another shape's nearest "
        "answer: with the 24,000-step model shipped before the current one 0.2% of held-out lone "
        "parts and of 648 held-out partial assemblies, and 55% of 33 shapes of no known category "
        "lie past it)."))
    unfamiliar_diversity: bool = Field(default=False, description=(
        "When true, a query whose g answer lies further than `unfamiliar_diversity_ratio` times the "
        "familiarity threshold from the training bank (so it gets the `unfamiliar_shape` warning, "
        "`familiarity_check`) and that gives no `region` is answered as the `diversity` gallery "
        "(round-robin over g's modes by weight) instead of in `suggest_order`: where the model is "
        "guessing, one part of each kind it proposes lies closer to what is missing than several of "
        "the kind it rates first. Off by default because the two benchmarks disagree "
        "(docs/training.md, \"Unfamiliar shapes\"): on furniture and airplanes nobody here made the "
        "best of the top 5 as placed comes closer to the component taken away (0.230 against 0.242 "
        "and 0.334 against 0.357; five random parts: 0.216 and 0.263), on the generator's held-out "
        "shapes functional mAP@5 falls from 0.922 to 0.916, and to 0.642 against 0.707 with every "
        "perturbation of the robustness table at once. Turn it on for collections unlike the "
        "generator's."))
    unfamiliar_diversity_ratio: float = Field(default=1.1, ge=1, description=(
        "How far past the familiarity threshold (as a factor) `unfamiliar_diversity` starts. "
        "Chosen on Scopia's and Kator & Legaz's furniture (`complementme evaluate-real --data "
        "data/real-train/processed`) and the generator's training-split queries: at 1 / 1.1 / "
        "1.25 / off the best of the top 5 as placed lay 0.216 / 0.229 / 0.258 / 0.285 from the "
        "component taken away (five random parts of the category: 0.209) and functional mAP@5 was "
        "0.920 / 0.922 / 0.923 / 0.923; held out, 1 cost 0.011 of mAP@5, 1.1 cost 0.006. Just "
        "past the threshold (the 0.99 quantile of training shapes' own distances) lie generated "
        "shapes g knows well."))
    diversity_min_mode_weight: float = Field(default=0.02, ge=0, le=1, description=(
        "In a `diversity` gallery, modes lighter than this join the round-robin only after the others "
        "ran out of parts."))
    assemble_max_parts: int = Field(default=8, ge=1, description=(
        "Parts `/assemble` adds to the start when the request gives no `max_parts`."))
    max_assemble_parts: int = Field(default=24, ge=1, description=(
        "Largest `max_parts` of an `/assemble` request."))
    assemble_candidates: int = Field(default=60, ge=1, description=(
        "Suggestions `/assemble` considers at each step (at most `max_k`): enough that the "
        "complementary kinds are among them when g's favourites are all already placed."))
    assemble_candidate_rounds: int = Field(default=3, ge=1, le=10, description=(
        "Rounds of `assemble_candidates` suggestions one `/assemble` step may ask for: when every "
        "likely candidate of a round does the job of a part already placed, the next round asks for "
        "the following ones (the tested parts excluded)."))
    assemble_min_mode_weight: float = Field(default=0.02, ge=0, le=1, description=(
        "`/assemble` stops when no candidate's mode has at least this weight phi_k."))
    assemble_max_distance: float = Field(default=4.0, gt=0, description=(
        "`/assemble` stops when no candidate lies within this distance of its mode's mean, in "
        "root-mean-square standard deviations of that mode (1 = a typical draw from it)."))
    assemble_duplicate_distance: float = Field(default=0.03, ge=0, description=(
        "`/assemble` skips a candidate whose placed samples lie within this Chamfer distance "
        "(object radius units) of a part already placed: the same geometry at the same spot."))
    assemble_duplicate_centre: float = Field(default=0.05, ge=0, description=(
        "`/assemble` also skips a candidate whose placed box is centred within this distance of a "
        "placed part's box, unless it encloses a much smaller part (see "
        "`assemble_duplicate_contain_ratio`)."))
    assemble_duplicate_size_ratio: float = Field(default=1.5, ge=1, description=(
        "Extents within this factor count as the same (same size, same profile)."))
    assemble_duplicate_contain_ratio: float = Field(default=7.0, ge=1, description=(
        "At the same spot (see `assemble_duplicate_centre`) only a candidate whose box holds a "
        "placed part's box, with at least this times its volume and another profile across its "
        "longest axis, is a new part (a hull around its deck); any other candidate there is a "
        "duplicate (a tyre on a hub, a longer rod on a shorter one, crossing or nested boxes)."))
    assemble_cover_distance: float = Field(default=0.05, ge=0, description=(
        "`/assemble` skips a candidate when at least `assemble_cover_share` of its placed samples "
        "lie within this distance of the placed parts' samples: it adds little new surface."))
    assemble_cover_share: float = Field(default=0.5, ge=0, le=1, description=(
        "Share of a candidate's samples near placed surface that makes it redundant (1: rule off)."))
    assemble_cover_quantile: float = Field(default=0.9, ge=0, le=1, description=(
        "Where a category's own parts lie on each other's surface, the cover rule follows the data: "
        "its share becomes the larger of `assemble_cover_share` and this quantile of the shares of "
        "the category's training parts, each measured against the rest of its shape (rifle "
        "magazines and bodies, boat cabins lie half on other parts; chair parts do not). 0: "
        "`assemble_cover_share` everywhere."))
    assemble_cover_shapes: int = Field(default=300, ge=1, description=(
        "Training shapes of a category `/assemble` reads at most (a seeded draw), for "
        "`assemble_cover_quantile` and for the missing-spot rule (`assemble_gap_neighbours`): the "
        "shipped catalog has at most 144 training shapes per category, read once per process "
        "(13-80 ms a category, made for every shipped category by the warm-up; 75-370 ms before "
        "the cover shares were compiled) and kept across catalog writes, which add no training "
        "shapes; a catalog grown by writes costs no more."))
    assemble_overlap_iou: float = Field(default=0.25, ge=0, le=1, description=(
        "`/assemble` skips a candidate whose placed box overlaps a placed part's box with more than "
        "this IoU when the two parts do the same job (see `assemble_same_job_sigmas`)."))
    assemble_same_job_sigmas: float = Field(default=2.6, ge=0, description=(
        "Two overlapping parts do the same job when their embeddings lie within this root-mean-square "
        "distance of each other, in the standard deviations g predicts for the candidate's mode "
        "at that step (g would take either for the other). The scale follows g's sigmas: 1.8 for "
        "the model shipped before (sigmas about 0.060), 2.6 for the shipped one (about 0.049), "
        "chosen on 360 starts of the training split (`evaluate-assembly --split train --starts 40 "
        "--no-contact`: 73% / 75% / 76% / 79% / 75% good at 1.8 / 2.0 / 2.2 / 2.6 / 3.0, stacked "
        "7.5% / 5.0% / 4.2% / 1.4% / 0.8%; docs/modeling.md)."))
    assemble_strong_overlap_iou: float = Field(default=0.5, ge=0, le=1, description=(
        "Boxes overlapping with more than this IoU count as the same job at the wider embedding "
        "distance `assemble_strong_overlap_sigmas` (a second roof over the roof, of another "
        "style: further apart than `assemble_same_job_sigmas`)."))
    assemble_strong_overlap_sigmas: float = Field(default=3.9, ge=0, description=(
        "Embedding distance (RMS standard deviations of the candidate's mode) within which two "
        "parts whose boxes overlap past `assemble_strong_overlap_iou` do the same job. Chosen with "
        "it on 360 training starts (`evaluate-assembly --split train --starts 40 --no-contact`, "
        "the rule off: 81.4% good, 3.3% stacked): IoU 0.5 with 3.9 (1.5 times "
        "`assemble_same_job_sigmas`) 82.2% / 2.2%; with 3.25 / 5.2: 81.7% / 2.8%, 82.2% / 2.5%; "
        "IoU 0.6 with 3.9: 81.4% / 3.3%; IoU 0.4 with 5.2: 77.5% (cars 53%: car bodies are "
        "several overlapping pieces); docs/modeling.md."))
    assemble_overlap_mode_distance: float = Field(default=2.3, ge=0, description=(
        "Boxes overlapping past `assemble_overlap_iou` also do the same job when the placed part "
        "lies within this root-mean-square distance of the candidate's mode's mean, in that "
        "mode's standard deviations: the kind of part the mode proposes is already there (a "
        "second roof shifted along the first, its style too far from the first's for "
        "`assemble_same_job_sigmas`). 0: off. Chosen on 360 training starts (`evaluate-assembly "
        "--split train --starts 40 --no-contact`): off / 2.0 / 2.3 / 2.55: 82.5% / 82.5% / 82.5% / "
        "81.9% good (stacked 1.7% at each but 2.55); for the 512-point h candidate 81.4% / 81.4% / "
        "82.2% / 81.9% (stacked 3.6% / 3.6% / 2.8% / 2.2%); docs/modeling.md."))
    assemble_complete_margin: float = Field(default=0.0, description=(
        "`/assemble` stops (`complete`) when no eligible candidate's mixture log-likelihood "
        "exceeds the most likely placed part's by more than this: g's most wanted complement is "
        "one the assembly already has."))
    assemble_open_mode_weight: float = Field(default=0.15, ge=0, le=1, description=(
        "Before `/assemble` calls an assembly complete, a mode of g's mixture with at least this "
        "weight that no placed part explains (see `assemble_open_mode_distance`) and that has "
        "an eligible candidate gets that candidate: g still expects a kind of part the assembly "
        "lacks (a rifle's magazine under a mode of bipods and scopes). 0: off. Chosen with "
        "`assemble_open_mode_distance` on 360 training starts (`evaluate-assembly --split train "
        "--starts 40 --no-contact`): 79.4% good runs off; 80.0-81.4% at 0.05-0.2 and 0.75-2.0, "
        "best 0.15 and 1.0 (81.4%, stacked 3.3% against 2.5%; docs/modeling.md)."))
    assemble_open_mode_margin: float = Field(default=20.0, ge=0, description=(
        "The candidate an unmet mode gives (see `assemble_open_mode_weight`) must have a mixture "
        "log-likelihood within this of the most likely placed part's: far less likely parts of "
        "a lighter mode (a seat block under a finished chair's seat) are not added. Chosen on "
        "360 training starts: 5 / 10 / 20 / 40 / none gave 81.1 / 82.2 / 82.5 / 82.2 / 82.2% "
        "good runs, 1.7 / 1.7 / 1.7 / 1.9 / 2.2% stacked (docs/modeling.md)."))
    assemble_open_mode_distance: float = Field(default=1.0, gt=0, description=(
        "A placed part explains a mode of g's mixture (see `assemble_open_mode_weight`) when its "
        "embedding lies within this root-mean-square distance of the mode's mean, in the mode's "
        "standard deviations."))
    assemble_gap_neighbours: int = Field(default=10, ge=0, description=(
        "Before an `/assemble` step ends `complete`, the assembly compares the placed parts with "
        "this many of the category's training shapes that hold them most closely; where at least "
        "`assemble_gap_share` of those shapes (counting only those with more components than the "
        "assembly has parts) have a component the placed parts leave uncovered (see "
        "`assemble_gap_uncovered`), it asks for suggestions placed at that spot and adds the first "
        "that does no placed part's job (`service.modeling.templates`; labels are not read). 0: off. "
        "Chosen on 360 training starts (`evaluate-assembly --split train --starts 40 --no-contact`, "
        "docs/modeling.md): 85.3% good runs against 82.2% off; with 5 or 20 shapes 84.2%, 84.7%."))
    assemble_gap_share: float = Field(default=0.5, gt=0, le=1, description=(
        "Share of the `assemble_gap_neighbours` shapes that must have an uncovered component at a "
        "spot for the spot to count as missing (0.6 / 0.7 / 0.8: 84.7 / 83.9 / 83.1% good runs on "
        "the training starts)."))
    assemble_gap_uncovered: float = Field(default=0.5, gt=0, le=1, description=(
        "A template shape's component is uncovered when fewer than this share of its samples lie "
        "within `assemble_cover_distance` of the placed parts' samples (0.3 / 0.7: 83.6 / 84.7% "
        "good runs on the training starts)."))
    assemble_gap_radius: float = Field(default=0.15, gt=0, description=(
        "Uncovered components centred closer than this (object radius units) vote for one spot, "
        "and the suggestions asked for a spot are those placed within this distance of it "
        "(0.1 / 0.2: 84.4% good runs on the training starts)."))
    assemble_gap_max_distance: float = Field(default=1.2, gt=0, description=(
        "A part the missing-spot rule adds (see `assemble_gap_neighbours`) lies within this distance "
        "of its mode's mean, in root-mean-square standard deviations of that mode (other steps: "
        "`assemble_max_distance`): g did not ask for it, so it must at least be a typical draw. "
        "Chosen on the training starts: 1.1 to 1.6 gave the same good runs (85.0%) with fewer parts "
        "added to finished objects; 1.0 / 0.9: 84.7 / 83.9%."))
    assemble_complete_quantiles: tuple[float, float] = Field(default=(0.5, 0.9), description=(
        "Quantiles of the part count of the catalog's shapes of the assembly's category: "
        "`/assemble` calls an assembly with fewer parts than the first never complete on g's word "
        "alone, and one with as many as the second complete (no shape of the data has many more)."))
    assemble_frame_tolerance: float = Field(default=0.1, ge=0, le=1, description=(
        "`/assemble` calls an assembly complete only when it spans the complete object's frame: "
        "its box centred within this distance of the origin and its surface reaching radius "
        "1 minus this (the canonical frame centres every complete object's box and scales it to "
        "radius 1)."))
    assemble_branch_min_distance: float = Field(default=0.05, ge=0, description=(
        "Siblings of an `/assemble` tree whose placed samples lie within this Chamfer distance of "
        "each other count as one alternative: the next candidate is shown instead."))
    assemble_max_nodes: int = Field(default=63, ge=1, description=(
        "Most parts placed over a whole `branching` tree of `/assemble` (its size bound)."))
    max_assemble_branching: int = Field(default=4, ge=1, description=(
        "Largest `branching` (children per state) of an `/assemble` request."))
    max_export_parts: int = Field(default=200, ge=1, description="Most parts one `/export` request may give.")

    # --- limits on requests -----------------------------------------------------------------
    min_points: int = Field(default=16, ge=1, description="Fewest points a query may have.")
    max_points: int = Field(default=100_000, ge=1, description="Most points a query may have.")
    default_k: int = Field(default=10, ge=1, description="Suggestions returned when a request gives no `k`.")
    max_k: int = Field(default=100, ge=1, description="Largest `k` a request may ask for.")
    max_place_parts: int = Field(default=100, ge=1, description=(
        "Most part ids one `/place` request may give."))
    max_exclude: int = Field(default=1000, ge=0, description=(
        "Most part ids plus shape ids one request may exclude."))
    max_batch_items: int = Field(default=64, ge=1, description=(
        "Most queries in one `/suggest/batch` request."))
    max_request_cost_ms: float = Field(default=2000.0, gt=0, description=(
        "Budget of one suggestion request (`/suggest`, `/suggest/mesh`, `/suggest/batch`) in "
        "estimated CPU milliseconds, checked before any work starts (413 `over_budget`). Each query "
        "is estimated at 4 ms, plus 0.05 ms per 1000 points, plus 0.35 ms per suggestion (k) when "
        "`refine_contact` is on (measured on the shipped artifacts: 30 ms of CPU for k = 100 "
        "refined), "
        "plus 5 ms per 256 `region_candidates` when the query gives a `region`. The default "
        "admits one query of any k with refinement, and a batch of 64 without."))
    max_body_bytes: int = Field(default=8 * 1024 * 1024, ge=1024, description=(
        "Largest JSON request body in bytes (checked against Content-Length before reading "
        "and enforced while reading)."))
    max_upload_bytes: int = Field(default=32 * 1024 * 1024, ge=1024, description=(
        "Largest multipart mesh upload in bytes (whole request body)."))
    max_mesh_vertices: int = Field(default=2_000_000, ge=3, description=(
        "Most vertices an uploaded mesh may have."))
    max_mesh_faces: int = Field(default=2_000_000, ge=1, description="Most faces an uploaded mesh may have.")
    max_mesh_nodes: int = Field(default=10_000, ge=1, description=(
        "Most scene nodes an uploaded mesh may have and reach (glTF nodes, counted once per path "
        "from a scene root, so instancing counts; OBJ groups and objects); checked before a scene is "
        "built: a 2 MB GLB of 100k instancing nodes took 28 s of CPU to build."))
    max_mesh_nesting: int = Field(default=64, ge=4, description=(
        "Deepest nesting of an uploaded glTF's JSON and of its node tree, checked before either is "
        "read: a 4 KB glTF nested 2,000 deep crashed the JSON reader, a 40k-deep node chain took 34 s."))
    upload_memory_bytes: int = Field(default=8 * 1024 * 1024, ge=1, description=(
        "A multipart upload's file part stays in memory while it is received up to this size; a "
        "larger one spills to a temporary file (Starlette's own bound is 1 MiB). The spill is "
        "what a few-MB mesh's form costs: the bench's 3.8 MB OBJ took 17.5 ms to receive and "
        "parse as a form spilled to disk, 6.6 ms in memory (in process), and its request 33.1 "
        "against 29.6 ms p50 at 8 MiB (docs/performance.md, section e). The uploads being "
        "received hold at most `max_receiving_bytes` together."))
    max_receiving_bytes: int = Field(default=256 * 1024 * 1024, ge=1024, description=(
        "Bytes that request bodies being received may hold at once, per server process. Bodies "
        "are read before a request takes its place in the overload gate; each reserves what it "
        "can bring (its Content-Length, or its limit, `max_body_bytes` or `max_upload_bytes`, "
        "when it sends none) until it is in, and a request that finds the reservations full is "
        "refused 503 `overloaded` with Retry-After before a byte of its body is read. A body "
        "larger than this is let in when no other is being received. Without it only the proxy's "
        "connection limit bounded the memory (or, past `upload_memory_bytes`, disk) held by "
        "bodies in reception."))
    max_receiving_bytes_per_client: int = Field(default=64 * 1024 * 1024, ge=1024, description=(
        "Share of `max_receiving_bytes` one client (address; behind a proxy, `X-Forwarded-For` "
        "from a trusted one) may hold with bodies still arriving; past it the client's next "
        "request with a body is refused 429 `too_many_bodies` with Retry-After before a byte is "
        "read, and other clients are not touched. So a client with many slow uploads cannot take "
        "the whole reception budget. A single body larger than this is let in when the client has "
        "none on its way."))
    max_concurrent_uploads: int = Field(default=2, ge=1, description=(
        "Mesh uploads (`/suggest/mesh`, `/assemble/mesh`) parsed at once per server process; more "
        "wait for a turn (within the request deadline). Parsing an 18 MB OBJ peaks at about 0.4 GB, "
        "so this bounds the memory uploads can take."))
    max_body_points: int = Field(default=100_000, ge=1, description=(
        "Most `[x, y, z]` triples one JSON body may hold, all `/suggest/batch` items together (by "
        "default as many as one query may have: 100k points take orjson about 30 ms to parse). "
        "Counted by the body's `[` while it is read, so a larger body is refused (422 "
        "`too_many_points`) before any of it is parsed: an 8.3 MB body of 1.04M points held the "
        "event loop (and `/healthz`) for 1.4-1.7 s."))
    max_page_size: int = Field(default=500, ge=1, description="Largest `limit` of a `GET /parts` page.")

    # --- catalog additions (docs/catalog.md) --------------------------------------------------
    data_dir: Path | None = Field(default=None, description=(
        "Folder of catalog additions: an SQLite database (the source of truth), the added parts' "
        "geometry files and the derived index. Unset (with the `sqlite` backend): the catalog is "
        "read-only and the write endpoints answer 403."))
    api_key: SecretStr | None = Field(default=None, description=(
        "Key that catalog writes must carry as `Authorization: Bearer <key>` (at least 16 "
        "characters). Unset: catalog writes are refused with 403."))
    cors_origins: list[str] = Field(default_factory=list, description=(
        'Origins a browser may call the API from, as a JSON list (`["https://app.example"]`); '
        "empty: no CORS headers are sent."))
    max_added_parts: int = Field(default=100_000, ge=0, description=(
        "Most parts the data folder may hold (deleted ones not counted); further additions get 507."))
    max_part_extent: float = Field(default=3.0, gt=0, description=(
        "Largest bounding-box diagonal of an added part in the canonical frame (the complete "
        "object has unit radius); larger uploads are refused, usually a mesh in other units "
        "sent without its `frame`."))
    catalog_poll_seconds: float = Field(default=2.0, ge=0, description=(
        "How often the server looks for additions made by other processes on the same data folder "
        "(other server processes, `complementme catalog add --data-dir`), or, with the `postgres` backend, "
        "asks the database for changes it was not notified of (LISTEN/NOTIFY brings them at once; "
        "this is the fallback); 0: never (with `postgres`: notifications alone)."))
    catalog_backend: Literal["sqlite", "postgres"] = Field(default="sqlite", description=(
        "Where added parts live. `sqlite`: the data folder (`data_dir`) of one machine. `postgres`: "
        "a PostgreSQL database (`database_url`) shared by any number of replicas, each of which "
        "takes writes and follows the others' changes (docs/catalog.md, docs/deploy.md); "
        "`data_dir` is not used then."))
    database_url: SecretStr | None = Field(default=None, description=(
        "With the `postgres` backend: the database's connection URL, "
        "`postgresql://USER:PASSWORD@HOST:5432/DBNAME` (libpq parameters such as `sslmode` may "
        "follow as `?sslmode=require`). Kept secret: never logged or shown."))
    database_migrate: bool = Field(default=False, description=(
        "Apply the database's schema migrations at start (idempotent, under a lock, so replicas "
        "starting together apply each once). Off: a database whose schema is not the one this "
        "version needs refuses the start, and `complementme catalog migrate` applies them."))
    database_pool_size: int = Field(default=4, ge=1, le=100, description=(
        "Most connections to the database per server process (writes and catch-up reads; the "
        "LISTEN connection of the replica is one more)."))
    database_timeout: float = Field(default=5.0, gt=0, le=300, description=(
        "Seconds a catalog write waits for a database connection, to connect, or for the lock "
        "that orders writes across replicas; past it the write answers 503 `database_unavailable` "
        "with Retry-After and nothing is stored."))
    database_retry_after: int = Field(default=5, ge=1, le=3600, description=(
        "Seconds the Retry-After header of a 503 `database_unavailable` asks a client to wait."))
    write_commit_margin: float = Field(default=5.0, ge=0, description=(
        "Seconds of its deadline (`request_timeout`) that an addition must still have when it is "
        "about to commit (at most half the timeout is used): a later one is rolled back and answered "
        "504 with nothing stored, so that a 504 never hides a stored part. What follows the commit "
        "(a rename, the snapshot swap, the answer) takes milliseconds."))

    # --- overload ---------------------------------------------------------------------------
    max_inflight: int = Field(default=4, ge=1, description=(
        "Requests that run inference (every POST and DELETE but `POST /suggest` and catalog writes) "
        "handled at once; more wait in a queue."))
    max_inflight_suggest: int = Field(default=64, ge=1, description=(
        "`POST /suggest` requests handled at once, in a gate of their own: they wait in the "
        "micro-batcher's queue, whose workers bound the CPU they use, so many may be in flight; "
        "more wait in a queue (`max_queue`)."))
    max_inflight_writes: int = Field(default=2, ge=1, description=(
        "Catalog writes (POST /parts, DELETE /parts/...) handled at once, in a gate of their own so "
        "that suggestion queries never wait behind writes."))
    max_queue: int = Field(default=32, ge=0, description=(
        "Requests that may wait for an inference slot; past this the service answers 503 with "
        "Retry-After at once."))
    overload_refusal_delay: float = Field(default=0.5, ge=0, le=10, description=(
        "Seconds a request refused with 503 `overloaded` (or 429 `too_many_errors`) waits (on no "
        "CPU) before its answer. "
        "Clients that retry at once, ignoring Retry-After, then come back a few times a second "
        "each instead of hundreds: 128 such clients of `/suggest` on one server process made 840 refusals a "
        "second without it and cut goodput to 60% of that at concurrency 32."))
    client_error_burst: int = Field(default=100, ge=0, description=(
        "Error answers (4xx) one client (address) may get in a row before its requests are "
        "refused with 429 `too_many_errors` (before their body is read; `Retry-After`, held "
        "`overload_refusal_delay` like a 503); the budget refills at `client_error_rate`. So a "
        "flood of cheap invalid requests cannot starve other clients (docs/catalog.md, "
        "\"Overload\"). Per server process; the probes are never refused. Behind a proxy, clients "
        "are told apart only "
        "by `X-Forwarded-For` from an address in uvicorn's `FORWARDED_ALLOW_IPS`. 0: no limit."))
    client_error_rate: float = Field(default=20.0, gt=0, description=(
        "Error answers a second that refill a client's budget (`client_error_burst`)."))
    body_read_timeout: float = Field(default=10.0, gt=0, description=(
        "Seconds a request body may go without a byte arriving; past this it is answered 408 "
        "`body_timeout` (a client that stalls, or declared a Content-Length longer than what it "
        "sent). Bodies are read before a request takes its place in the overload gate, so slow "
        "clients never hold a slot (only their body's share of `max_receiving_bytes`)."))
    request_timeout: float = Field(default=30.0, gt=0, description=(
        "Seconds a request may take (queueing included); past this it is answered 504 (503 if it "
        "was still queued) and its late answer is dropped."))

    @field_validator("assemble_complete_quantiles")
    @classmethod
    def _quantiles(cls, value: tuple[float, float]) -> tuple[float, float]:
        if not 0 <= value[0] <= value[1] <= 1:
            raise ValueError("assemble_complete_quantiles must be two quantiles 0 <= low <= high <= 1")
        return value

    @field_validator("api_key", "database_url", mode="before")
    @classmethod
    def _empty_key_is_unset(cls, value: object) -> object:
        return None if value == "" else value

    @field_validator("api_key")
    @classmethod
    def _long_enough(cls, value: SecretStr | None) -> SecretStr | None:
        if value is not None and len(value.get_secret_value()) < 16:
            raise ValueError("api_key must be at least 16 characters (use a random token)")
        return value

    @model_validator(mode="after")
    def _backend_has_its_database(self) -> Settings:
        if self.catalog_backend == "postgres" and self.database_url is None:
            raise ValueError("catalog_backend postgres needs database_url (COMPLEMENTME_DATABASE_URL)")
        return self

    @property
    def catalog_enabled(self) -> bool:
        """Whether this server stores added parts at all (a data folder, or the database)."""
        return self.catalog_backend == "postgres" or self.data_dir is not None

    @property
    def limits(self) -> Limits:
        """The request limits among these settings, with their checks."""
        return Limits(min_points=self.min_points, max_points=self.max_points, default_k=self.default_k,
                      max_k=self.max_k, max_exclude=self.max_exclude, max_batch_items=self.max_batch_items)


def check_point_count(n: int, min_points: int, max_points: int) -> None:
    """``too_few_points`` below ``min_points``, ``too_many_points`` over ``max_points`` points."""
    if n < min_points:
        raise InputError("too_few_points", f"{n} points given, at least {min_points} are needed")
    if n > max_points:
        raise InputError("too_many_points", f"{n} points given, at most {max_points} are accepted")


@dataclass(frozen=True)
class Limits:
    """What one suggestion request may ask, and the one check of each limit.

    Each check raises the ``InputError`` a client sees (code and message). The request schemas
    (``service.api.schemas``) apply them to what arrives over HTTP; the engine applies the same
    ones to the points and options of in-process callers (the CLI, the benchmark, training's
    evaluation), which reach it without a schema.
    """

    min_points: int
    max_points: int
    default_k: int
    max_k: int
    max_exclude: int
    max_batch_items: int

    def check_point_count(self, n: int) -> None:
        """``too_few_points`` or ``too_many_points`` outside ``[min_points, max_points]``."""
        check_point_count(n, self.min_points, self.max_points)

    def k(self, k: int | None) -> int:
        """The query's k (``default_k`` when not given); ``k_out_of_range`` outside ``[1, max_k]``."""
        k = self.default_k if k is None else k
        if not 1 <= k <= self.max_k:
            raise InputError("k_out_of_range", f"k must be between 1 and {self.max_k}, found {k}")
        return k

    def check_exclusions(self, n: int) -> None:
        """``too_many_exclusions`` over ``max_exclude`` excluded part and shape ids."""
        if n > self.max_exclude:
            raise InputError("too_many_exclusions", f"at most {self.max_exclude} part and shape ids may be "
                             "excluded per request")

    def check_batch_items(self, n: int) -> None:
        """``empty_batch`` or ``too_many_items`` outside ``[1, max_batch_items]``."""
        if n == 0:
            raise InputError("empty_batch", "items is empty; send at least one query")
        if n > self.max_batch_items:
            raise InputError("too_many_items", f"{n} items given, at most {self.max_batch_items} are "
                             "accepted")


@lru_cache
def get_settings() -> Settings:
    """The process's settings, read once from the environment (``cache_clear()`` to re-read)."""
    return Settings()


def _env_default(name: str) -> str:
    field = Settings.model_fields[name]
    if name == "artifacts":
        return "`exported/` at the repository root"
    value = field.default_factory() if field.default_factory is not None else field.default  # type: ignore[call-arg]
    if value is None:
        return "unset"
    if isinstance(value, bool):
        return "`true`" if value else "`false`"
    return f"`{value}`"


def render_settings_markdown() -> str:
    """The settings table for the docs, generated from the field descriptions above."""
    lines = [
        "# Service settings",
        "",
        "<!-- Generated by `python -m service.settings > docs/settings.md`; do not edit by hand. -->",
        "",
        f"Every setting is an environment variable with the prefix `{ENV_PREFIX}`.",
        "",
        "| Variable | Default | Meaning |",
        "|---|---|---|",
    ]
    for name, field in Settings.model_fields.items():
        desc = (field.description or "").replace("|", "\\|")
        lines.append(f"| `{ENV_PREFIX}{name.upper()}` | {_env_default(name)} | {desc} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.stdout.write(render_settings_markdown())
