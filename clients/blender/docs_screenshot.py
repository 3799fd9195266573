r"""Take docs/blender.md's screenshot: the add-on's panel in Blender's window, under Xvfb.

With a service running (``complementme serve``) and the add-on zip made, from the repository root:

    python3 clients/blender/make_addon_zip.py
    CM_ADDON_ZIP=clients/blender/dist/complementme_blender.zip CM_URL=http://127.0.0.1:8000 \
    CM_SHOT=/tmp/blender-panel.png BLENDER_USER_SCRIPTS=$(mktemp -d) BLENDER_USER_CONFIG=$(mktemp -d) \
    xvfb-run -a -s "-screen 0 1280x720x24" blender --factory-startup --enable-event-simulate \
        -p 0 0 1280 720 --python clients/blender/docs_screenshot.py
    python3 -c "from PIL import Image; Image.open('/tmp/blender-panel.png').convert('RGB').quantize(128, \
        dither=Image.Dither.NONE).save('docs/blender-panel.png', optimize=True)"   # 242 kB -> 72 kB

It builds the partial chair of the in-Blender test (seat and back from primitives), presses
Suggest, imports the first suggestion, opens the sidebar on the ComplementMe tab and saves the
3D view as a PNG, then quits. Blender draws with Mesa's software OpenGL under Xvfb; the
simulated events (``--enable-event-simulate``) close the first-run splash and pick the tab.
"""

from __future__ import annotations

import os
from typing import Any

import bpy

ADDON = "complementme_blender"
state: dict[str, Any] = {"step": 0}


def view3d() -> tuple[Any, Any, Any]:
    window = bpy.context.window_manager.windows[0]
    area = next(a for a in window.screen.areas if a.type == "VIEW_3D")
    region = next(r for r in area.regions if r.type == "WINDOW")
    return window, area, region


def build_scene() -> None:
    bpy.ops.preferences.addon_install(filepath=os.path.abspath(os.environ["CM_ADDON_ZIP"]), overwrite=True)
    bpy.ops.preferences.addon_enable(module=ADDON)
    bpy.context.preferences.addons[ADDON].preferences.server_url = os.environ["CM_URL"]
    for obj in list(bpy.data.objects):
        if obj.type == "MESH":
            bpy.data.objects.remove(obj)
    bpy.ops.mesh.primitive_cube_add(size=1, location=(0.0, 0.0, 0.45), scale=(0.46, 0.46, 0.05))
    bpy.context.object.name = "seat"
    bpy.ops.mesh.primitive_cube_add(size=1, location=(-0.21, 0.0, 0.72), scale=(0.04, 0.46, 0.5))
    bpy.context.object.name = "back"
    for obj in bpy.data.objects:
        obj.select_set(obj.type == "MESH")
    bpy.context.scene.complementme.category = "chair"


def tick() -> float | None:
    """One step per timer call, so that Blender redraws between them."""
    window, area, region = view3d()
    step = state["step"]
    state["step"] += 1
    with bpy.context.temp_override(window=window, area=area, region=region):
        if step == 0:
            # Close the first-run splash (Quick Setup) the way a user would, with Esc.
            window.event_simulate(type="ESC", value="PRESS")
            window.event_simulate(type="ESC", value="RELEASE")
            build_scene()
            assert bpy.ops.complementme.suggest() == {"FINISHED"}
            assert bpy.ops.complementme.import_suggestion(index=0) == {"FINISHED"}
            space = area.spaces.active
            space.show_region_ui = True
            space.overlay.show_floor = True
            space.shading.color_type = "RANDOM"
            for obj in bpy.data.objects:
                obj.select_set(obj.type == "MESH")
            bpy.ops.view3d.view_selected()
            bpy.ops.view3d.view_orbit(angle=0.4, type="ORBITLEFT")
            return 1.0
        if step in (1, 2, 3):
            for obj in bpy.data.objects:
                obj.select_set(False)
            # Blender 3.4 has no API for the sidebar's tab: Ctrl + wheel over its tab strip (the
            # right edge; over a field it would change the field) steps to the next tab (Item,
            # Tool, View, ComplementMe), sent as a simulated event, one per redraw.
            sidebar = next(r for r in area.regions if r.type == "UI")
            x, y = sidebar.x + sidebar.width - 8, sidebar.y + sidebar.height - 40
            window.event_simulate(type="MOUSEMOVE", value="NOTHING", x=x, y=y)
            window.event_simulate(type="WHEELDOWNMOUSE", value="PRESS", x=x, y=y, ctrl=True)
            return 0.5
        bpy.ops.screen.screenshot_area(filepath=os.path.abspath(os.environ["CM_SHOT"]))
        bpy.ops.wm.quit_blender()
        return None


bpy.app.timers.register(tick, first_interval=1.0)
