"""Authors the fixture scene stage (geometry, materials, lights, animated camera).

Runs with usd-core in ``.venv-usd``. The scene is what Blender's Cycles renders;
the render settings, products and vars are authored separately (see
``fixtures.py``) once the product files exist.
"""

from __future__ import annotations

import math

from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux, UsdShade

FIRST_FRAME = 1001
LAST_FRAME = 1006
WIDTH = 128
HEIGHT = 72
# 16:9 film back in mm so that the render's aspect needs no conform.
H_APERTURE = 36.0
V_APERTURE = 20.25
FOCAL_LENGTH = 30.0
INSERT_PRIM = "/World/Insert"


def _material(
    stage: Usd.Stage, path: str, color: tuple[float, float, float], roughness: float
):
    mat = UsdShade.Material.Define(stage, path)
    shader = UsdShade.Shader.Define(stage, path + "/Surface")
    shader.CreateIdAttr("UsdPreviewSurface")
    shader.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(*color))
    shader.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(roughness)
    mat.CreateSurfaceOutput().ConnectToSource(shader.ConnectableAPI(), "surface")
    return mat


def _bind(prim: Usd.Prim, mat: UsdShade.Material) -> None:
    UsdShade.MaterialBindingAPI.Apply(prim).Bind(mat)


def _box_mesh(stage: Usd.Stage, path: str, h: float) -> UsdGeom.Mesh:
    mesh = UsdGeom.Mesh.Define(stage, path)
    pts = [(x, y, z) for z in (-h, h) for y in (-h, h) for x in (-h, h)]
    faces = [
        (0, 2, 3, 1),
        (4, 5, 7, 6),
        (0, 1, 5, 4),
        (2, 6, 7, 3),
        (0, 4, 6, 2),
        (1, 3, 7, 5),
    ]
    mesh.CreatePointsAttr(pts)
    mesh.CreateFaceVertexCountsAttr([4] * 6)
    mesh.CreateFaceVertexIndicesAttr([i for f in faces for i in f])
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    return mesh


def _sphere_mesh(
    stage: Usd.Stage, path: str, r: float, rings: int = 16, segs: int = 32
) -> UsdGeom.Mesh:
    mesh = UsdGeom.Mesh.Define(stage, path)
    pts = [(0.0, 0.0, -r)]
    for i in range(1, rings):
        th = math.pi * i / rings - math.pi / 2
        for j in range(segs):
            ph = 2 * math.pi * j / segs
            pts.append(
                (
                    r * math.cos(th) * math.cos(ph),
                    r * math.cos(th) * math.sin(ph),
                    r * math.sin(th),
                )
            )
    pts.append((0.0, 0.0, r))
    top = len(pts) - 1
    counts, idx = [], []
    for j in range(segs):
        counts.append(3)
        idx += [0, 1 + (j + 1) % segs, 1 + j]
    for i in range(rings - 2):
        a, b = 1 + i * segs, 1 + (i + 1) * segs
        for j in range(segs):
            counts.append(4)
            idx += [a + j, a + (j + 1) % segs, b + (j + 1) % segs, b + j]
    last = 1 + (rings - 2) * segs
    for j in range(segs):
        counts.append(3)
        idx += [last + j, last + (j + 1) % segs, top]
    mesh.CreatePointsAttr(pts)
    mesh.CreateFaceVertexCountsAttr(counts)
    mesh.CreateFaceVertexIndicesAttr(idx)
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.catmullClark)
    return mesh


def camera_eye(frame: float) -> Gf.Vec3d:
    """World position of the camera at ``frame`` (a lateral dolly with a push-in)."""
    t = frame - FIRST_FRAME
    return Gf.Vec3d(-0.6 + 0.25 * t, -7.0 + 0.15 * t, 4.2)


def author_scene(path: str) -> None:
    """Writes the scene (Z up, metres, 24 fps, frames 1001-1006) to ``path``."""
    stage = Usd.Stage.CreateNew(path)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    stage.SetStartTimeCode(FIRST_FRAME)
    stage.SetEndTimeCode(LAST_FRAME)
    stage.SetTimeCodesPerSecond(24)
    stage.SetFramesPerSecond(24)
    world = UsdGeom.Xform.Define(stage, "/World")
    stage.SetDefaultPrim(world.GetPrim())

    floor_mat = _material(stage, "/World/Looks/Floor", (0.55, 0.5, 0.45), 0.8)
    red_mat = _material(stage, "/World/Looks/Red", (0.7, 0.12, 0.08), 0.5)
    blue_mat = _material(stage, "/World/Looks/Blue", (0.1, 0.25, 0.7), 0.3)

    floor = UsdGeom.Mesh.Define(stage, "/World/Floor")
    s = 40.0
    floor.CreatePointsAttr([(-s, -s, 0), (s, -s, 0), (s, s, 0), (-s, s, 0)])
    floor.CreateFaceVertexCountsAttr([4])
    floor.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    floor.CreateNormalsAttr([(0, 0, 1)] * 4)
    floor.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
    floor.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    _bind(floor.GetPrim(), floor_mat)

    # Meshes, not UsdGeom.Cube/Sphere: Blender's USD importer drops material
    # bindings on implicit shapes.
    cube = _box_mesh(stage, "/World/Box", 0.6)
    xf = UsdGeom.XformCommonAPI(cube)
    xf.SetTranslate(Gf.Vec3d(-0.9, 0.4, 0.6))
    xf.SetRotate(Gf.Vec3f(0, 0, 25))
    _bind(cube.GetPrim(), red_mat)

    # The inserted object: a sphere marked for harmonization.
    sphere = _sphere_mesh(stage, INSERT_PRIM, 0.55)
    UsdGeom.XformCommonAPI(sphere).SetTranslate(Gf.Vec3d(0.9, -0.3, 0.55))
    sphere.GetPrim().CreateAttribute(
        "harmonizer:insert", Sdf.ValueTypeNames.Bool, custom=True
    ).Set(True)
    _bind(sphere.GetPrim(), blue_mat)

    sun = UsdLux.DistantLight.Define(stage, "/World/Sun")
    sun.CreateIntensityAttr(100.0)
    sun.CreateAngleAttr(2.0)
    UsdGeom.XformCommonAPI(sun).SetRotate(Gf.Vec3f(35, 0, 30))

    cam = UsdGeom.Camera.Define(stage, "/World/Cam")
    cam.CreateFocalLengthAttr(FOCAL_LENGTH)
    cam.CreateHorizontalApertureAttr(H_APERTURE)
    cam.CreateVerticalApertureAttr(V_APERTURE)
    cam.CreateClippingRangeAttr(Gf.Vec2f(0.1, 1000.0))
    cxf = UsdGeom.XformCommonAPI(cam)
    # Pitched down 58 degrees from the horizon so the floor fills the frame.
    cxf.SetRotate(Gf.Vec3f(58.0, 0.0, 6.0))
    for f in range(FIRST_FRAME, LAST_FRAME + 1):
        cxf.SetTranslate(camera_eye(f), Usd.TimeCode(f))
    stage.GetRootLayer().Save()


if __name__ == "__main__":
    import sys

    author_scene(sys.argv[1])
