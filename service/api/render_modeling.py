"""Assembly results to JSON-ready dicts matching ``schemas_modeling`` (checked by the tests)."""

from __future__ import annotations

from typing import Any

import numpy as np

from service.api.render import part_links, render_frame, render_placed
from service.artifacts.catalog import Catalog
from service.modeling.assembly import ADD_REASONS, STOP_REASONS, AssembleResult, Node


def render_node(n: Node, cat: Catalog, result: AssembleResult) -> dict[str, Any]:
    """One placed part, mapped from the canonical frame to the result's frame."""
    frame = result.frame
    s = n.suggestion
    i = s.part_index
    t = n.translation.reshape(1, 3)
    sc = np.asarray(s.scale, dtype=np.float64)   # the assembly suggests in the canonical frame
    lo, hi = frame.box_from_canonical(t + sc * cat.bbox_min[i], t + sc * cat.bbox_max[i])
    return {
        "node": n.node, "parent": n.parent, "depth": n.depth, "part_id": s.part_id, "shape_id": s.shape_id,
        "category": s.category, "label": s.label, "score": s.score, "mode": s.mode,
        "mode_weight": s.mode_weight, "distance": n.distance, "stop_reason": n.stop_reason,
        "added_by": n.added_by, "added_message": ADD_REASONS[n.added_by],
        **render_placed(s.part_id, frame.from_canonical(t)[0],
                        n.contact_offset @ frame.rotation * frame.radius, lo[0], hi[0],
                        sc @ np.abs(frame.rotation)),
    }


def render_assemble(result: AssembleResult, cat: Catalog, model_version: str, strategy: str,
                    frame_fitted: bool = False) -> dict[str, Any]:
    """An assembly as ``AssembleResponse``; ``cat``: the catalog it was grown on."""
    frame, start = result.frame, result.start
    start_out: dict[str, Any] = {"kind": start.kind}
    if start.part_index is not None:
        pid = cat.part_ids[start.part_index]
        placed = frame.from_canonical(result.start_translation[None])[0]
        start_out.update(part_id=pid, translation=[float(x) for x in placed], links=part_links(pid))
    else:
        start_out["points"] = len(start.points)
        start_out["parts"] = len(start.parts)
    nodes = [render_node(n, cat, result) for n in result.nodes]
    chain = {n.node for n in result.steps}
    return {
        "model_version": model_version, "frame": render_frame(frame), "start": start_out,
        "category": result.category, "strategy": strategy, "stop_reason": result.stop_reason,
        "stop_message": STOP_REASONS[result.stop_reason], "frame_fitted": frame_fitted,
        "steps": [d for d in nodes if d["node"] in chain], "nodes": nodes,
        "timings": {k: round(v, 6) for k, v in result.timings.items()},
    }
