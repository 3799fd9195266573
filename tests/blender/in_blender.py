"""Runs inside Blender (``blender --background --factory-startup --python-exit-code 1 --python``).

Driven by ``test_blender_addon.py``, which starts a real ``complementme serve`` and passes, in
the environment: ``CM_ADDON_ZIP`` (the add-on zip), ``CM_URL`` (the service), ``CM_SERVER_PID``
(to stop it at the end) and ``CM_RESULT`` (a JSON file this script writes for the test to read).
Any failed assertion ends Blender with exit code 1.

Steps: install and enable the add-on from its zip; build a partial chair (seat and back) from
primitives, z up; Suggest; import the first suggestion and compare the new object's world box
with the answer's ``bbox_min``/``bbox_max``; Auto-complete and compare every imported step the
same way; then the errors: a 4xx answer, a server that never answers, a stopped server.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import struct
import sys
import time
import urllib.parse
import urllib.request
from typing import Any

import bpy

ADDON = "complementme_blender"
BOX_TOLERANCE = 1e-3  # times the frame's radius: OBJ text keeps 8 digits, Blender stores float32


def world_box(obj: bpy.types.Object) -> tuple[list[float], list[float]]:
    pts = [obj.matrix_world @ v.co for v in obj.data.vertices]
    return [min(p[i] for p in pts) for i in range(3)], [max(p[i] for p in pts) for i in range(3)]


def assert_close(found: list[float], expected: list[float], tol: float, what: str) -> None:
    worst = max(abs(a - b) for a, b in zip(found, expected, strict=True))
    assert worst <= tol, f"{what}: found {found}, expected {expected} (off by {worst:.2e} > {tol:.2e})"


def assert_upright(obj: bpy.types.Object, url: str, entry: dict[str, Any], scale: float, tol: float) -> None:
    """Every vertex is where a z-up scene must draw the part's canonical vertex (x, y, z):
    at translation + scale * (x, -z, y) (y up becomes z up, front +x stays +x), times the part's
    per-axis fitting ``scale`` (along the scene's axes; [1, 1, 1] when the answer has none).

    Read from the service's OBJ here, vertex by vertex, so that a mirrored or turned part fails
    even where its box would look the same.
    """
    part_id = entry["part_id"]
    sx, sy, sz = entry.get("scale") or (1.0, 1.0, 1.0)
    path = "/parts/" + urllib.parse.quote(part_id, safe="/") + "/mesh?format=obj"
    with urllib.request.urlopen(url + path, timeout=30) as answer:
        canonical = [tuple(map(float, line.split()[1:4])) for line in answer.read().decode().splitlines()
                     if line.startswith("v ")]
    assert len(canonical) == len(obj.data.vertices), (len(canonical), len(obj.data.vertices))
    tx, ty, tz = entry["translation"]
    for v, c in zip(obj.data.vertices, canonical, strict=True):
        expected = [tx + scale * sx * c[0], ty - scale * sy * c[2], tz + scale * sz * c[1]]
        assert_close(list(obj.matrix_world @ v.co), expected, tol, f"{part_id} vertex {v.index}")


def glb_position_box(glb: bytes) -> tuple[list[float], list[float]]:
    """The POSITION accessor's min and max of the GLB the add-on sent."""
    length, kind = struct.unpack_from("<I4s", glb, 12)
    assert kind == b"JSON", f"GLB's first chunk must be JSON, found {kind!r}"
    doc = json.loads(glb[20:20 + length])
    acc = doc["accessors"][doc["meshes"][0]["primitives"][0]["attributes"]["POSITION"]]
    return acc["min"], acc["max"]


def expect_error(operator: Any, *needles: str) -> str:
    """Run an operator that must fail; its report (the RuntimeError Blender raises) must hold the needles."""
    try:
        operator()
    except RuntimeError as exc:
        text = str(exc)
    else:
        raise AssertionError(f"{operator} should have reported an error")
    assert "Traceback" not in text, f"the report is a traceback: {text}"
    for needle in needles:
        assert needle in text, f"expected {needle!r} in the report, found {text!r}"
    return text.strip()


def main() -> None:
    result: dict[str, Any] = {"blender": bpy.app.version_string}
    bpy.ops.preferences.addon_install(filepath=os.environ["CM_ADDON_ZIP"], overwrite=True)
    bpy.ops.preferences.addon_enable(module=ADDON)
    assert ADDON in bpy.context.preferences.addons, "the add-on did not enable"
    prefs = bpy.context.preferences.addons[ADDON].preferences
    prefs.server_url = os.environ["CM_URL"]

    # Spy on the client's calls (the real ones run) to compare Blender's objects with the answers.
    from complementme_blender import service_client

    calls: list[tuple[str, bytes, dict[str, Any], dict[str, Any]]] = []
    attempts: list[str] = []
    for name in ("suggest_mesh", "assemble_mesh"):
        real = getattr(service_client.Client, name)

        def spy(self: Any, glb: bytes, options: dict[str, Any], _real: Any = real, _name: str = name) -> Any:
            attempts.append(_name)
            answer = _real(self, glb, options)
            calls.append((_name, glb, options, answer))
            return answer
        setattr(service_client.Client, name, spy)

    # A partial chair from primitives, in metres, z up, front +x: a seat 0.45 m high and a back.
    for obj in list(bpy.data.objects):
        bpy.data.objects.remove(obj)
    bpy.ops.mesh.primitive_cube_add(size=1, location=(0.0, 0.0, 0.45), scale=(0.46, 0.46, 0.05))
    bpy.context.object.name = "seat"
    bpy.ops.mesh.primitive_cube_add(size=1, location=(-0.21, 0.0, 0.72), scale=(0.04, 0.46, 0.5))
    bpy.context.object.name = "back"
    for obj in bpy.data.objects:
        obj.select_set(True)
    scene = bpy.context.scene
    settings = scene.complementme
    settings.category, settings.k, settings.frame_mode = "chair", 5, "GROUND"

    # Suggest: the selection goes in world coordinates, with the z-up frame of the ground mode.
    assert bpy.ops.complementme.suggest() == {"FINISHED"}
    name, glb, options, answer = calls[-1]
    lo, hi = glb_position_box(glb)
    assert_close(lo, [-0.23, -0.23, 0.425], 1e-5, "the GLB's box (world coordinates)")
    assert_close(hi, [0.23, 0.23, 0.97], 1e-5, "the GLB's box (world coordinates)")
    frame = options["frame"]
    assert frame["up_axis"] == "z", frame
    assert_close(frame["center"], [0.0, 0.0, 0.485], 1e-5, "frame centre (box down to the ground)")
    radius = (0.23 ** 2 + 0.23 ** 2 + 0.485 ** 2) ** 0.5
    assert abs(frame["radius"] - radius) < 1e-5, f"frame radius {frame['radius']}, expected {radius}"
    assert answer["frame"]["up_axis"] == "z", answer["frame"]
    assert abs(answer["frame"]["scale"] - radius) < 1e-5, answer["frame"]
    assert len(settings.suggestions) == len(answer["suggestions"]) == 5, len(settings.suggestions)
    assert settings.warning == "", (settings.warning, answer["warnings"])  # a chair: nothing to doubt
    result["suggestions"] = [(s["rank"], s["part_id"], s["label"], round(s["score"], 2))
                             for s in answer["suggestions"]]

    # Import the first suggestion: a new object named after the part, on the answer's box.
    before = set(bpy.data.objects)
    assert bpy.ops.complementme.import_suggestion(index=0) == {"FINISHED"}
    new = list(set(bpy.data.objects) - before)
    first = answer["suggestions"][0]
    assert len(new) == 1 and new[0].name == first["part_id"], [o.name for o in new]
    found_lo, found_hi = world_box(new[0])
    tol = BOX_TOLERANCE * radius
    assert_close(found_lo, first["bbox_min"], tol, f"{first['part_id']} box min")
    assert_close(found_hi, first["bbox_max"], tol, f"{first['part_id']} box max")
    assert_close(list(new[0].matrix_world.translation), first["translation"], tol, "object origin")
    assert_upright(new[0], os.environ["CM_URL"], first, radius, tol)
    result["imported"] = {"name": new[0].name, "bbox_min": found_lo, "bbox_max": found_hi}

    # Auto-complete from seat and back: every step becomes an object on its step's box.
    for obj in bpy.data.objects:
        obj.select_set(obj.name in ("seat", "back"))
    before = set(bpy.data.objects)
    assert bpy.ops.complementme.autocomplete() == {"FINISHED"}
    name, _, options, answer = calls[-1]
    assert name == "assemble_mesh" and options["frame"] == frame, options
    new = sorted(set(bpy.data.objects) - before, key=lambda o: o.name)
    steps = answer["steps"]
    assert steps and len(new) == len(steps), (len(new), len(steps))
    by_part = {}
    for obj in new:
        by_part.setdefault(obj["complementme_part_id"], []).append(obj)
    for step in steps:
        obj = by_part[step["part_id"]].pop()
        found_lo, found_hi = world_box(obj)
        assert_close(found_lo, step["bbox_min"], tol, f"step {step['part_id']} box min")
        assert_close(found_hi, step["bbox_max"], tol, f"step {step['part_id']} box max")
        assert_upright(obj, os.environ["CM_URL"], step, radius, tol)
        assert obj["complementme_added_by"] == step["added_by"], (obj["complementme_added_by"], step)
    result["assembled"] = [(s["part_id"], s["label"]) for s in steps]

    # A torus is no known kind of shape: the answer's unfamiliar_shape warning reaches the panel.
    bpy.ops.mesh.primitive_torus_add(location=(3.0, 0.0, 0.3), major_radius=0.3, minor_radius=0.08)
    torus = bpy.context.object
    for obj in bpy.data.objects:
        obj.select_set(obj is torus)
    settings.category = ""
    assert bpy.ops.complementme.suggest() == {"FINISHED"}
    codes = [w["code"] for w in calls[-1][3]["warnings"]]
    assert "unfamiliar_shape" in codes, codes
    assert "training shape" in settings.warning, settings.warning
    result["torus_warning"] = settings.warning
    bpy.data.objects.remove(torus)
    for obj in bpy.data.objects:
        obj.select_set(obj.name in ("seat", "back"))

    # The frame fitted by the service: only the up axis is sent, with fit_frame; the answer's
    # frame (fitted, z up) places the imported part.
    settings.category, settings.frame_mode = "chair", "FIT"
    assert bpy.ops.complementme.suggest() == {"FINISHED"}
    _, _, options, answer = calls[-1]
    assert options["frame"] == {"up_axis": "z"} and options["fit_frame"] is True, options
    assert answer["frame_fitted"] is True and answer["frame"]["up_axis"] == "z", answer["frame"]
    fitted_radius = answer["frame"]["scale"]
    before = set(bpy.data.objects)
    assert bpy.ops.complementme.import_suggestion(index=0) == {"FINISHED"}
    (new_obj,) = set(bpy.data.objects) - before
    first = answer["suggestions"][0]
    found_lo, found_hi = world_box(new_obj)
    assert_close(found_lo, first["bbox_min"], BOX_TOLERANCE * fitted_radius, "fitted frame: box min")
    assert_close(found_hi, first["bbox_max"], BOX_TOLERANCE * fitted_radius, "fitted frame: box max")
    result["fitted"] = {"frame": answer["frame"], "labels": [s["label"] for s in answer["suggestions"]]}
    bpy.data.objects.remove(new_obj)
    settings.frame_mode = "GROUND"
    for obj in bpy.data.objects:
        obj.select_set(obj.name in ("seat", "back"))

    # Errors, in the report area: the service's 4xx message ...
    settings.category = "no-such-category"
    result["error_4xx"] = expect_error(bpy.ops.complementme.suggest, "422", "unknown_category")
    settings.category = "chair"
    # ... a server that accepts the connection and never answers (1 s timeout) ...
    with socket.socket() as silent:
        silent.bind(("127.0.0.1", 0))
        silent.listen(4)
        prefs.server_url, prefs.timeout = f"http://127.0.0.1:{silent.getsockname()[1]}", 1.0
        result["error_timeout"] = expect_error(bpy.ops.complementme.suggest, "no answer within 1 s")
    # ... Blender's online-access preference (4.2+; faked here on older Blender): no call at all ...
    from complementme_blender import ui

    class _Offline:
        class app:  # noqa: N801 - stands for bpy.app
            online_access = False

    real_bpy, ui.bpy, n_attempts = ui.bpy, _Offline(), len(attempts)
    try:
        result["error_offline"] = expect_error(bpy.ops.complementme.suggest, "online access is disabled")
    finally:
        ui.bpy = real_bpy
    assert len(attempts) == n_attempts, "a call was attempted with online access off"
    # ... and the real server, stopped.
    prefs.server_url, prefs.timeout = os.environ["CM_URL"], 30.0
    stop_server(int(os.environ["CM_SERVER_PID"]), os.environ["CM_URL"])
    result["error_stopped"] = expect_error(bpy.ops.complementme.suggest, "connection refused")
    result["error_import_stopped"] = expect_error(lambda: bpy.ops.complementme.import_suggestion(index=0),
                                                  "connection refused")
    with open(os.environ["CM_RESULT"], "w") as f:
        json.dump(result, f, indent=1)


def stop_server(pid: int, url: str) -> None:
    """SIGTERM the service and wait until its port refuses connections (at most 30 s)."""
    host, port = url.rsplit("/", 1)[-1].rsplit(":", 1)
    os.kill(pid, signal.SIGTERM)
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        try:
            socket.create_connection((host, int(port)), timeout=1).close()
        except OSError:
            return
        time.sleep(0.1)
    raise AssertionError(f"the service (pid {pid}) still accepts connections 30 s after SIGTERM")


if __name__ == "__main__":
    main()
    sys.stdout.flush()
