"""ComplementMe for Blender: suggest the next part of a partial shape, and import it placed.

A sidebar panel in the 3D view (N panel, tab "ComplementMe") sends the selected objects to a
ComplementMe service as one GLB (``POST /suggest/mesh``), lists the suggestions, and imports a
chosen part (``GET /parts/{id}/mesh``) where the service places it; "Auto-complete" grows the
shape with ``POST /assemble/mesh``. Python's standard library only: nothing is installed at run
time. The modules ``service_client`` and ``geometry`` do not import ``bpy`` (they are tested
outside Blender); ``ui`` holds everything that does.
"""

bl_info = {
    "name": "ComplementMe",
    "author": "ComplementMe service authors",
    "version": (0, 1, 0),
    "blender": (3, 4, 0),
    "location": "View3D > Sidebar > ComplementMe",
    "description": "Suggest and place the next part of a partial shape with a ComplementMe service",
    "category": "3D View",
}


def register() -> None:
    from . import ui

    ui.register()


def unregister() -> None:
    from . import ui

    ui.unregister()
