"""Motion blur's shutter, shared by the camera and the geometry: an object's matrix_world at the
shutter's open and close from its keyframed transform, whether an object is animated, and the
warnings for the motion KD Trace does not blur."""
from __future__ import annotations

import numpy as np


def motion_warnings(depsgraph, warnings: list, motion_handled: set) -> None:
    """With motion blur on: objects that move over the shutter and are not in `motion_handled`
    (moved by parents, constraints or drivers, lights, realised objects) are named, and so
    are meshes that deform (only an object's transform is blurred)."""
    scene = depsgraph.scene
    if not scene.render.use_motion_blur:
        return
    for obj in scene.objects:
        if obj.type in ("MESH", "CURVE", "FONT", "SURFACE", "META", "LIGHT") and \
                is_animated(obj) and obj.name not in motion_handled:
            _, problem = over_shutter(scene, obj)
            warnings.append(f"object '{obj.name}': " + (
                problem or "object motion blur is not rendered (the object is rendered where "
                           "it is at the frame)"))
        elif obj.type == "MESH" and _deforms(obj):
            warnings.append(f"object '{obj.name}': its deformation over the shutter is not "
                            "blurred (only the object's transform)")


def _deforms(obj) -> bool:
    """Whether the mesh may deform over time: animated shape keys or an armature."""
    keys = obj.data.shape_keys
    return (keys is not None and keys.animation_data is not None) or \
        any(m.type == "ARMATURE" for m in obj.modifiers)


def is_animated(obj) -> bool:
    """Whether the object's transform is animated (keyframes or drivers, its own or a parent's)."""
    while obj is not None:
        anim = obj.animation_data
        if anim is not None and (anim.action is not None or len(anim.drivers)):
            return True
        obj = obj.parent
    return False


def over_shutter(scene, obj):
    """((matrix_world at the shutter's open, at its close) or None when the object (a
    camera too) does not move, a problem or None). The shutter is open for Motion Blur >
    Shutter frames, starting at, centred on or ending at the frame (Position); the object's own
    keyframed location, rotation and scale are evaluated at both ends (parents, constraints
    and drivers are not)."""
    if not is_animated(obj):
        return None, None
    anim = obj.animation_data
    if obj.parent is not None or len(obj.constraints) or \
            anim is None or anim.action is None or len(anim.drivers):
        return None, "motion blur from parents, constraints or drivers is not rendered"
    r = scene.render
    frame = scene.frame_current + scene.frame_subframe
    shutter = r.motion_blur_shutter
    start = {"START": frame, "CENTER": frame - 0.5 * shutter, "END": frame - shutter}[
        r.motion_blur_position]
    ends = [_animated_matrix(obj, anim.action, t) for t in (start, start + shutter)]
    if ends[0] is None:
        return None, "motion blur from this animation (delta transforms, axis-angle) is not rendered"
    return tuple(ends), None


def _animated_matrix(obj, action, time):
    """The object's matrix_world at `time` from its action's location, rotation (Euler or
    quaternion) and scale curves and its current values for the others; None when the action
    animates something else of the transform (delta transforms, axis-angle)."""
    from mathutils import Euler, Matrix, Quaternion, Vector
    values = {"location": list(obj.location), "rotation_euler": list(obj.rotation_euler),
              "rotation_quaternion": list(obj.rotation_quaternion), "scale": list(obj.scale)}
    for curve in _action_curves(action, obj):
        if curve.data_path not in values:
            if curve.data_path.startswith(("delta_", "rotation_axis_angle")):
                return None
            continue
        values[curve.data_path][curve.array_index] = curve.evaluate(time)
    if obj.rotation_mode == "QUATERNION":
        rotation = Quaternion(values["rotation_quaternion"]).normalized().to_matrix()
    elif obj.rotation_mode == "AXIS_ANGLE":
        return None
    else:
        rotation = Euler(values["rotation_euler"], obj.rotation_mode).to_matrix()
    return np.array(Matrix.LocRotScale(Vector(values["location"]), rotation,
                                       Vector(values["scale"])), np.float64)


def _action_curves(action, obj):
    """The F-curves of an action (layered actions of Blender 4.4+ too)."""
    curves = getattr(action, "fcurves", None)
    if curves is not None and len(curves):
        return list(curves)
    out = []
    for layer in getattr(action, "layers", ()):
        for strip in layer.strips:
            slot = obj.animation_data.action_slot
            bag = strip.channelbag(slot) if slot is not None else None
            if bag is not None:
                out += list(bag.fcurves)
    return out
