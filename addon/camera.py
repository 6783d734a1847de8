"""The scene camera as core.scene's Camera (projection, thin lens, its transform over the
shutter), and the image it renders: its size after the resolution percentage and the render
border."""
from __future__ import annotations

import numpy as np

from ..core.scene.model import Camera, SceneError
from .motion import over_shutter


def render_size(scene) -> tuple[int, int]:
    """The image size in pixels after the resolution percentage."""
    r = scene.render
    return (max(1, r.resolution_x * r.resolution_percentage // 100),
            max(1, r.resolution_y * r.resolution_percentage // 100))


def render_region(scene) -> tuple[int, int, int, int]:
    """The render border as (x0, y0, x1, y1) pixels, top-left origin; the whole image without one."""
    width, height = render_size(scene)
    r = scene.render
    if not r.use_border:
        return (0, 0, width, height)
    x0, x1 = int(r.border_min_x * width), int(r.border_max_x * width)
    # Blender's border is measured from the bottom; ours from the top.
    y0, y1 = height - int(r.border_max_y * height), height - int(r.border_min_y * height)
    if x1 <= x0 or y1 <= y0:
        raise SceneError("the render border is empty")
    return (x0, y0, x1, y1)


def export_camera(depsgraph, warnings: list) -> Camera:
    """The scene camera: projection, thin lens (depth of field) and, with motion blur on, its
    transform at the shutter's close. What is not rendered of it gets one warning."""
    scene = depsgraph.scene
    if scene.camera is None:
        raise SceneError("the scene has no active camera")
    camera = scene.camera.evaluated_get(depsgraph)
    width, height = render_size(scene)
    r = scene.render
    # Blender's own projection already holds sensor fit, shift and pixel aspect.
    projection = np.array(camera.calc_matrix_camera(
        depsgraph, x=width, y=height, scale_x=r.pixel_aspect_x, scale_y=r.pixel_aspect_y))
    data = camera.data
    if data.type not in ("ORTHO", "PERSP"):
        raise SceneError(f"camera type {data.type} is not supported (use perspective or orthographic)")
    kind = data.type
    (sx, sy), offset = projection_ndc(kind, projection)
    to_world = np.array(camera.matrix_world.normalized(), np.float64)
    if not (np.isfinite(to_world).all() and
            np.allclose(np.linalg.norm(to_world[:3, :3], axis=0), 1.0, atol=1e-4)):
        raise SceneError(f"camera '{scene.camera.name}' has a transform that is NaN, infinite "
                         "or scaled to 0 on an axis: it has no view to render")
    problems = []
    lens = {}
    dof = data.dof
    if dof.use_dof:
        if kind != "PERSP":
            problems.append("depth of field of an orthographic camera is not rendered")
        else:
            # Cycles' thin lens: radius = focal length / (2 f-stop), in metres (mm / 1000).
            lens["aperture"] = data.lens * 1e-3 / (2.0 * max(dof.aperture_fstop, 1e-5))
            lens["focus_distance"] = max(_focus_distance(camera, dof), 1e-6)
            lens["blades"] = int(dof.aperture_blades) if dof.aperture_blades >= 3 else 0
            lens["blade_rotation"] = float(dof.aperture_rotation)
            if abs(dof.aperture_ratio - 1.0) > 1e-6:
                problems.append(f"aperture ratio {dof.aperture_ratio:g} is rendered as 1")
    end = None
    if scene.render.use_motion_blur:
        shutter, problem = over_shutter(scene, scene.camera)
        if problem:
            problems.append(problem)
        if shutter is not None:
            to_world, end = (_normalized(m) for m in shutter)
    if problems:
        warnings.append(f"camera '{scene.camera.name}': " + "; ".join(problems))
    return Camera(kind, to_world, (sx, sy), offset, data.clip_start, data.clip_end,
                  to_world_end=end, **lens)


def projection_ndc(kind: str, projection: np.ndarray) -> tuple:
    """(ndc_scale, ndc_offset) of core.scene.model.Camera from an OpenGL projection matrix of
    Blender's (a camera's calc_matrix_camera, a viewport's window_matrix): sensor fit, shift
    and aspect are in it."""
    sx, sy = 1.0 / projection[0, 0], 1.0 / projection[1, 1]
    if kind == "ORTHO":
        return (sx, sy), (-projection[0, 3] * sx, -projection[1, 3] * sy)
    return (sx, sy), (projection[0, 2] * sx, projection[1, 2] * sy)


def _focus_distance(camera, dof) -> float:
    """Distance of the plane in focus along the view axis (Cycles': to the focus object's
    origin, else the Focus Distance)."""
    if dof.focus_object is None:
        return float(dof.focus_distance)
    m = camera.matrix_world.normalized()
    view_axis = np.array(m.col[2][:3])
    target = np.array(dof.focus_object.matrix_world.translation)
    return float(abs(view_axis @ (np.array(m.translation) - target)))


def _normalized(matrix: np.ndarray) -> np.ndarray:
    """The 4x4 matrix with unit axes (a camera's transform without its scale)."""
    from mathutils import Matrix
    return np.array(Matrix(matrix.tolist()).normalized(), np.float64)
