"""Blender side of the add-on: preferences, scene settings, the three operators and the panel.

Calls are synchronous with the timeout of the preferences (a suggestion on the shipped model
answers in well under a second on loopback); Blender waits for them like for any operator.
Every failure is reported with ``self.report({'ERROR'}, ...)`` and the operator is cancelled:
the user reads one line in the status bar and the Info editor, never a traceback.
"""

from __future__ import annotations

import textwrap
from typing import Any

import bpy
from bpy.props import (
    CollectionProperty,
    EnumProperty,
    FloatProperty,
    FloatVectorProperty,
    IntProperty,
    PointerProperty,
    StringProperty,
)
from mathutils import Matrix

from .geometry import FRAME_MODES, frame_request, glb_bytes, parse_obj, part_scale, placement_matrix
from .service_client import Client, ServiceError

ADDON = __package__ or "complementme_blender"
PART_ID_KEY = "complementme_part_id"  # custom property on imported objects
ADDED_BY_KEY = "complementme_added_by"  # ... and on auto-completed ones: the rule that added it


# -- settings --------------------------------------------------------------------------------

class ComplementMePreferences(bpy.types.AddonPreferences):
    """Where the service is. Kept in Blender's preferences, not in .blend files (the API key
    must not travel with a scene someone shares)."""

    bl_idname = ADDON

    server_url: StringProperty(name="Server URL", default="http://127.0.0.1:8000",  # type: ignore[valid-type]
                               description="Base URL of the ComplementMe service")
    api_key: StringProperty(name="API key", default="", subtype="PASSWORD",  # type: ignore[valid-type]
                            description="Optional: sent as 'Authorization: Bearer <key>'")
    timeout: FloatProperty(name="Timeout (s)", default=30.0, min=0.5, max=600.0,  # type: ignore[valid-type]
                           description="Seconds to wait for the service's answer")

    def draw(self, context: bpy.types.Context) -> None:
        col = self.layout.column()
        col.prop(self, "server_url")
        col.prop(self, "api_key")
        col.prop(self, "timeout")


class ComplementMeSuggestion(bpy.types.PropertyGroup):
    """One suggestion of the last answer (the gallery's rows)."""

    rank: IntProperty()  # type: ignore[valid-type]
    part_id: StringProperty()  # type: ignore[valid-type]
    label: StringProperty()  # type: ignore[valid-type]
    category: StringProperty()  # type: ignore[valid-type]
    score: FloatProperty()  # type: ignore[valid-type]
    translation: FloatVectorProperty(size=3)  # type: ignore[valid-type]
    part_scale: FloatVectorProperty(size=3, default=(1.0, 1.0, 1.0))  # type: ignore[valid-type]
    bbox_min: FloatVectorProperty(size=3)  # type: ignore[valid-type]
    bbox_max: FloatVectorProperty(size=3)  # type: ignore[valid-type]


class ComplementMeSettings(bpy.types.PropertyGroup):
    """The panel's options and the last answer, stored with the scene."""

    category: StringProperty(name="Category", default="",  # type: ignore[valid-type]
                             description="Only parts of this category (empty: any)")
    k: IntProperty(name="Count", default=5, min=1, max=50,  # type: ignore[valid-type]
                   description="How many suggestions to ask for")
    max_parts: IntProperty(name="Parts to add", default=0, min=0, max=24,  # type: ignore[valid-type]
                           description="Auto-complete: parts to add (0: the service's default)")
    frame_mode: EnumProperty(name="Frame", items=FRAME_MODES, default="GROUND",  # type: ignore[valid-type]
                             description="Where the complete object is, in scene units")
    frame_center: FloatVectorProperty(name="Centre", size=3, subtype="XYZ",  # type: ignore[valid-type]
                                      description="Centre of the complete object")
    frame_radius: FloatProperty(name="Radius", default=1.0, min=1e-6,  # type: ignore[valid-type]
                                description="Radius of the complete object")
    suggestions: CollectionProperty(type=ComplementMeSuggestion)  # type: ignore[valid-type]
    frame_scale: FloatProperty(default=1.0)  # type: ignore[valid-type]
    frame_rotation: FloatVectorProperty(size=9, default=(1, 0, 0, 0, 1, 0, 0, 0, 1))  # type: ignore[valid-type]
    model_version: StringProperty()  # type: ignore[valid-type]
    # What the last answer could not vouch for (a shape of no kind the model knows, a frame far
    # off, no sure category): its warnings' messages, shown above the suggestions.
    warning: StringProperty()  # type: ignore[valid-type]


# -- helpers -----------------------------------------------------------------------------------

def _client(context: bpy.types.Context) -> Client:
    """A client for the configured server, once Blender's online-access preference allows it."""
    # bpy.app.online_access exists from Blender 4.2 on (Preferences > System > Network); before
    # it, add-ons had no such switch, so access is allowed.
    if not getattr(bpy.app, "online_access", True):
        raise ServiceError("online access is disabled in Blender's preferences (System > Network > "
                           "Allow Online Access); ComplementMe needs it to reach the service")
    prefs = context.preferences.addons[ADDON].preferences
    return Client(prefs.server_url, prefs.api_key, prefs.timeout)


def _selected_meshes(context: bpy.types.Context) -> list[bpy.types.Object]:
    return [o for o in context.selected_objects if o.type in {"MESH", "CURVE", "SURFACE", "META", "FONT"}]


def _selection_glb(context: bpy.types.Context) -> tuple[bytes, tuple[Any, Any]]:
    """The selected objects (modifiers applied) in world coordinates as one GLB, and their box."""
    depsgraph = context.evaluated_depsgraph_get()
    positions: list[float] = []
    indices: list[int] = []
    for obj in _selected_meshes(context):
        evaluated = obj.evaluated_get(depsgraph)
        mesh = evaluated.to_mesh()
        try:
            mesh.transform(evaluated.matrix_world)
            mesh.calc_loop_triangles()
            co = [0.0] * (3 * len(mesh.vertices))
            mesh.vertices.foreach_get("co", co)
            tri = [0] * (3 * len(mesh.loop_triangles))
            mesh.loop_triangles.foreach_get("vertices", tri)
            offset = len(positions) // 3
            positions.extend(co)
            indices.extend(i + offset for i in tri)
        finally:
            evaluated.to_mesh_clear()
    if not indices:
        raise ServiceError("select at least one object with faces")
    lo = tuple(min(positions[i::3]) for i in range(3))
    hi = tuple(max(positions[i::3]) for i in range(3))
    return glb_bytes(positions, indices), (lo, hi)


def _frame_options(settings: ComplementMeSettings, box: tuple[Any, Any]) -> dict[str, object]:
    try:
        return frame_request(settings.frame_mode, box[0], box[1], tuple(settings.frame_center),
                             settings.frame_radius)
    except ValueError as exc:
        raise ServiceError(str(exc)) from None


def _store_frame(settings: ComplementMeSettings, frame: dict[str, Any]) -> None:
    settings.frame_scale = float(frame["scale"])
    settings.frame_rotation = [float(x) for row in frame["rotation"] for x in row]


def _stored_frame(settings: ComplementMeSettings) -> dict[str, object]:
    r = list(settings.frame_rotation)
    return {"scale": settings.frame_scale, "rotation": [r[0:3], r[3:6], r[6:9]]}


def add_part(context: bpy.types.Context, part_id: str, label: str, geometry: tuple[list[Any], list[Any]],
             frame: dict[str, object], translation: Any, scale: Any) -> bpy.types.Object:
    """Add a part as a new object named after it, placed by the service's answer.

    The mesh data stays centred in canonical units (as the service sends it); the object's
    matrix carries the placement, so the object's origin is the part's box centre.
    """
    vertices, faces = geometry
    mesh = bpy.data.meshes.new(part_id)
    mesh.from_pydata(vertices, [], faces)
    mesh.update()
    obj = bpy.data.objects.new(part_id, mesh)
    obj.matrix_world = Matrix(placement_matrix(frame, tuple(translation), tuple(scale)))
    obj[PART_ID_KEY] = part_id
    obj["complementme_label"] = label
    context.collection.objects.link(obj)
    return obj


def _part_geometry(client: Client, part_id: str) -> tuple[list[Any], list[Any]]:
    text = client.part_mesh_obj(part_id)
    try:
        return parse_obj(text)
    except ValueError as exc:
        raise ServiceError(f"part {part_id}: {exc}") from None


# -- operators ---------------------------------------------------------------------------------

class _ServiceOperator(bpy.types.Operator):
    """Runs ``work`` and turns every failure into a report: ServiceError as it is, anything else
    as one line naming the exception (a bug of ours, still not a traceback in the user's face)."""

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        return context.scene is not None and hasattr(context.scene, "complementme")

    def execute(self, context: bpy.types.Context) -> set[str]:
        try:
            message = self.work(context)
        except ServiceError as exc:
            self.report({"ERROR"}, f"ComplementMe: {exc}")
            return {"CANCELLED"}
        except Exception as exc:  # the report area, not a traceback
            self.report({"ERROR"}, f"ComplementMe: unexpected {type(exc).__name__}: {exc}")
            return {"CANCELLED"}
        self.report({"INFO"}, f"ComplementMe: {message}")
        return {"FINISHED"}

    def work(self, context: bpy.types.Context) -> str:
        raise NotImplementedError


class COMPLEMENTME_OT_suggest(_ServiceOperator):  # noqa: N801 - Blender\'s naming convention
    """Ask the service which parts complement the selected objects"""

    bl_idname = "complementme.suggest"
    bl_label = "Suggest"
    bl_options = {"REGISTER"}  # noqa: RUF012

    def work(self, context: bpy.types.Context) -> str:
        settings = context.scene.complementme
        client = _client(context)
        glb, box = _selection_glb(context)
        options: dict[str, Any] = {"k": settings.k, **_frame_options(settings, box)}
        if settings.category.strip():
            options["category"] = settings.category.strip()
        answer = client.suggest_mesh(glb, options)
        settings.suggestions.clear()
        for s in answer.get("suggestions", []):
            item = settings.suggestions.add()
            item.rank, item.part_id, item.score = int(s["rank"]), s["part_id"], float(s["score"])
            item.label, item.category = s.get("label") or "", s.get("category") or ""
            item.translation = s["translation"]
            item.part_scale = part_scale(s)
            item.bbox_min, item.bbox_max = s["bbox_min"], s["bbox_max"]
        _store_frame(settings, answer["frame"])
        settings.model_version = str(answer.get("model_version", ""))
        # The service marks the warnings that make its suggestions guesses (``guess``).
        doubts = [str(w.get("message", "")) for w in answer.get("warnings", []) if w.get("guess")]
        settings.warning = " ".join(doubts)
        if doubts:
            self.report({"WARNING"}, f"ComplementMe: the suggestions are guesses: {doubts[0]}")
        return f"{len(settings.suggestions)} suggestions"


class COMPLEMENTME_OT_import_suggestion(_ServiceOperator):  # noqa: N801 - Blender\'s naming convention
    """Import this suggested part, placed where the service puts it"""

    bl_idname = "complementme.import_suggestion"
    bl_label = "Import suggestion"
    bl_options = {"REGISTER", "UNDO"}  # noqa: RUF012

    index: IntProperty(name="Index", default=0, min=0)  # type: ignore[valid-type]

    def work(self, context: bpy.types.Context) -> str:
        settings = context.scene.complementme
        if self.index >= len(settings.suggestions):
            raise ServiceError("no such suggestion: press Suggest first")
        s = settings.suggestions[self.index]
        geometry = _part_geometry(_client(context), s.part_id)
        obj = add_part(context, s.part_id, s.label, geometry, _stored_frame(settings), s.translation,
                       s.part_scale)
        # Selected and active, so that the next Suggest counts it as part of the shape.
        obj.select_set(True)
        context.view_layer.objects.active = obj
        return f"imported {obj.name}"


class COMPLEMENTME_OT_autocomplete(_ServiceOperator):  # noqa: N801 - Blender\'s naming convention
    """Let the service grow the selected objects into a complete shape, and import every part"""

    bl_idname = "complementme.autocomplete"
    bl_label = "Auto-complete"
    bl_options = {"REGISTER", "UNDO"}  # noqa: RUF012

    def work(self, context: bpy.types.Context) -> str:
        settings = context.scene.complementme
        client = _client(context)
        glb, box = _selection_glb(context)
        options: dict[str, Any] = {**_frame_options(settings, box)}
        if settings.category.strip():
            options["category"] = settings.category.strip()
        if settings.max_parts > 0:
            options["max_parts"] = settings.max_parts
        answer = client.assemble_mesh(glb, options)
        steps = answer.get("steps", [])
        # Fetch every mesh before adding anything, so that a failure leaves the scene unchanged.
        geometry = {step["part_id"]: _part_geometry(client, step["part_id"]) for step in steps}
        names = []
        for step in steps:
            obj = add_part(context, step["part_id"], step.get("label") or "", geometry[step["part_id"]],
                           answer["frame"], step["translation"], part_scale(step))
            # Which rule of the assembly chose it (likely, unmet_mode, missing_spot: docs/api.md).
            obj[ADDED_BY_KEY] = step.get("added_by", "likely")
            names.append(obj.name)
        stop = answer.get("stop_reason")
        return f"added {len(names)} parts" + (f" (stopped: {stop})" if stop else "")


# -- panel -------------------------------------------------------------------------------------

class COMPLEMENTME_PT_panel(bpy.types.Panel):  # noqa: N801 - Blender\'s naming convention
    bl_label = "ComplementMe"
    bl_idname = "COMPLEMENTME_PT_panel"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "ComplementMe"

    def draw(self, context: bpy.types.Context) -> None:
        layout = self.layout
        prefs = context.preferences.addons[ADDON].preferences
        settings = context.scene.complementme
        layout.use_property_split = True
        layout.use_property_decorate = False
        col = layout.column()
        col.prop(prefs, "server_url", text="Server")
        col.prop(prefs, "api_key", text="Key")
        col.prop(settings, "category")
        col.prop(settings, "frame_mode")
        if settings.frame_mode == "MANUAL":
            col.prop(settings, "frame_center")
            col.prop(settings, "frame_radius")
        col.prop(settings, "k")
        col.operator(COMPLEMENTME_OT_suggest.bl_idname, icon="VIEWZOOM")
        col.separator()
        col.prop(settings, "max_parts")
        col.operator(COMPLEMENTME_OT_autocomplete.bl_idname, icon="MOD_BUILD")
        if not settings.suggestions:
            layout.label(text="Select the parts you have, then Suggest.", icon="INFO")
            return
        if settings.warning:
            warn = layout.box()
            warn.label(text="These suggestions are guesses:", icon="ERROR")
            for line in textwrap.wrap(settings.warning, 60)[:6]:
                warn.label(text=line)
        # The service has no thumbnail route: each row shows rank, label, score and the part id.
        box = layout.box()
        box.use_property_split = False
        for i, s in enumerate(settings.suggestions):
            row = box.row()
            row.label(text=f"{s.rank}. {s.label or s.category or 'part'}  {s.score:.1f}")
            op = row.operator(COMPLEMENTME_OT_import_suggestion.bl_idname, text="Import", icon="IMPORT")
            op.index = i
            box.label(text=f"    {s.part_id}")


CLASSES = (
    ComplementMePreferences,
    ComplementMeSuggestion,
    ComplementMeSettings,
    COMPLEMENTME_OT_suggest,
    COMPLEMENTME_OT_import_suggestion,
    COMPLEMENTME_OT_autocomplete,
    COMPLEMENTME_PT_panel,
)


def register() -> None:
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.Scene.complementme = PointerProperty(type=ComplementMeSettings)


def unregister() -> None:
    del bpy.types.Scene.complementme
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
