"""Run by a Python that has ``bpy`` (Blender as a module): import a BVH into a fresh factory-settings scene with the
importer's DEFAULT settings and print what a user would see as one JSON line. No skycap import: the Blender
environment holds only bpy (bpy 5.0 pins numpy < 2, the project needs numpy >= 2).

    python blender_import_check.py FILE.bvh FRAME [FRAME ...]
"""

import json
import sys

import bpy


def main() -> None:
    path, frames = sys.argv[1], [int(f) for f in sys.argv[2:]]
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    before = {"fps": scene.render.fps, "fps_base": scene.render.fps_base, "frame_start": scene.frame_start,
              "frame_end": scene.frame_end}
    assert bpy.ops.import_anim.bvh(filepath=path) == {"FINISHED"}  # every option at its default
    arm = next(o for o in scene.objects if o.type == "ARMATURE")
    action = arm.animation_data.action
    heads = {}
    for f in frames:
        scene.frame_set(f)
        heads[f] = {pb.name: list(arm.matrix_world @ pb.head) for pb in arm.pose.bones}
    print("RESULT " + json.dumps({
        "version": bpy.app.version_string, "before": before, "fps": scene.render.fps,
        "fps_base": scene.render.fps_base, "frame_start": scene.frame_start, "frame_end": scene.frame_end,
        "action_frame_range": list(action.frame_range), "bones": [b.name for b in arm.data.bones],
        "unit_scale": scene.unit_settings.scale_length, "heads": heads,
    }))


main()
