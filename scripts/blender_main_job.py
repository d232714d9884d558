"""The main job: reconstruct the bundled sample through the installed extension in headless Blender.

Usage::

    .venv/bin/python scripts/blender_main_job.py [--out out] [--resolution 128] [--samples 32]
                                                 [--size 640x480] [--zip dist/nkf_blender-0.1.0.zip]

1. builds the extension zip with Blender's own tool (``scripts/build_extension.py``) unless ``--zip``
   names one, then installs and enables it with ``bpy.ops.extensions.package_install_files``;
2. imports ``nkf_model/data/sample.ply`` (oriented points) with ``bpy.ops.wm.ply_import``;
3. runs ``bpy.ops.object.nkf_reconstruct`` (synchronous in headless Blender);
4. sets up a camera, lights, materials and a floor, shows the input points beside the mesh,
   renders a PNG preview with Cycles on the CPU, and saves the ``.blend`` and the mesh (PLY).

Outputs in ``--out``: ``sample_nkf.blend``, ``sample_nkf_mesh.ply``, ``sample_render.png``. Blender's
user folders (where the extension is installed) are ``OUT/blender-user``, never ``~/.config/blender``.
"""

from __future__ import annotations

import argparse
import math
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SAMPLE = ROOT / "nkf_model" / "data" / "sample.ply"
EXTENSION = "bl_ext.user_default.nkf_blender"


def parse_args(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=ROOT / "out", help="output folder (default out/)")
    ap.add_argument("--input", type=Path, default=SAMPLE, help="PLY point cloud with x y z nx ny nz")
    ap.add_argument("--up", default="Y", help="the input's up axis, for ply_import (default Y)")
    ap.add_argument("--forward", default="NEGATIVE_Z", help="the input's forward axis (default NEGATIVE_Z)")
    ap.add_argument("--zip", type=Path, default=None, help="use this extension zip instead of building one")
    ap.add_argument("--resolution", type=int, default=128, help="reconstruction grid resolution")
    ap.add_argument("--method", choices=("default", "NKF", "SPLINES"), default="default",
                    help="reconstruction method (default: the operator's default)")
    ap.add_argument("--samples", type=int, default=32, help="Cycles samples per pixel")
    ap.add_argument("--size", default="640x480", help="render size WIDTHxHEIGHT")
    return ap.parse_args(argv)


def build_zip(out: Path) -> Path:
    run = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "build_extension.py"), "--output-dir", str(out / "dist"),
         "--stage-dir", str(out / "build-extension"), "--no-bundle"],  # this venv has the dependencies
        capture_output=True, text=True,
    )
    if run.returncode != 0:
        sys.exit(f"building the extension failed:\n{run.stdout}{run.stderr}")
    return Path(run.stdout.strip().splitlines()[-1])


VIEW = (1.0, 0.25, 0.3)  # from the object towards the camera: its right side, a little behind, above


def world_bounds(objects):
    from mathutils import Vector

    corners = [o.matrix_world @ Vector(c) for o in objects for c in o.bound_box]
    lo = Vector([min(c[i] for c in corners) for i in range(3)])
    hi = Vector([max(c[i] for c in corners) for i in range(3)])
    return lo, hi


def view_vectors():
    """Unit vectors: towards the camera, and the image's right direction."""
    from mathutils import Vector

    back = Vector(VIEW).normalized()
    right = (-back).cross(Vector((0.0, 0.0, 1.0))).normalized()
    return back, right


def frame_camera(bpy, scene, target, lens: float = 85.0):
    """A camera on the VIEW side of ``target`` (a list of objects), framing all of them."""
    lo, hi = world_bounds(target)
    center = (lo + hi) / 2
    radius = (hi - lo).length / 2
    cam_data = bpy.data.cameras.new("Camera")
    cam_data.lens = lens
    cam = bpy.data.objects.new("Camera", cam_data)
    scene.collection.objects.link(cam)
    aspect = scene.render.resolution_x / scene.render.resolution_y
    fov_h = 2 * math.atan(cam_data.sensor_width / (2 * lens))
    fov_v = 2 * math.atan(math.tan(fov_h / 2) / aspect)
    dist = 0.82 * radius / math.tan(min(fov_h, fov_v) / 2)
    back, _right = view_vectors()
    cam.location = center + back * dist
    cam.rotation_euler = (center - cam.location).to_track_quat("-Z", "Y").to_euler()
    scene.camera = cam
    return lo, hi


def material(bpy, name, color, roughness=0.45):
    mat = bpy.data.materials.new(name)
    if mat.node_tree is None:  # Blender < 5.0 creates materials without nodes
        mat.use_nodes = True
    bsdf = mat.node_tree.nodes.get("Principled BSDF")
    bsdf.inputs["Base Color"].default_value = (*color, 1.0)
    bsdf.inputs["Roughness"].default_value = roughness
    mat.diffuse_color = (*color, 1.0)
    return mat


def points_display(bpy, source, offset, radius, mat):
    """A linked duplicate of ``source`` drawn as small spheres (Geometry Nodes: Mesh to Points).

    The source object and its mesh are not modified: the duplicate shares the mesh data and carries
    the modifier.
    """
    ob = bpy.data.objects.new(f"{source.name}_points", source.data)
    ob.matrix_world = source.matrix_world.copy()
    ob.location = ob.location + offset
    for c in source.users_collection:
        c.objects.link(ob)
    tree = bpy.data.node_groups.new("NKF points", "GeometryNodeTree")
    tree.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    tree.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    nodes, links = tree.nodes, tree.links
    gin, gout = nodes.new("NodeGroupInput"), nodes.new("NodeGroupOutput")
    to_points = nodes.new("GeometryNodeMeshToPoints")
    to_points.inputs["Radius"].default_value = radius
    set_mat = nodes.new("GeometryNodeSetMaterial")
    set_mat.inputs["Material"].default_value = mat
    links.new(gin.outputs["Geometry"], to_points.inputs["Mesh"])
    links.new(to_points.outputs["Points"], set_mat.inputs["Geometry"])
    links.new(set_mat.outputs["Geometry"], gout.inputs["Geometry"])
    mod = ob.modifiers.new("Points", "NODES")
    mod.node_group = tree
    return ob


def stage_scene(bpy, scene, source, result, samples: int, size: tuple[int, int]):
    """Materials, input points beside the mesh, floor, lights, camera, Cycles on the CPU."""
    result.data.materials.append(material(bpy, "NKF mesh", (0.80, 0.42, 0.18), 0.4))
    width = max(result.dimensions) or 1.0
    # The input points to the left of the mesh as the camera sees them.
    _back, right = view_vectors()
    lo, hi = world_bounds([result])
    span = abs((hi - lo).dot(right)) + 0.15 * width
    pts = points_display(bpy, source, -right * span, radius=0.0045 * width,
                         mat=material(bpy, "NKF points", (0.10, 0.35, 0.75), 0.5))
    bpy.context.view_layer.update()
    source.hide_render = True  # the loose vertices render as nothing anyway; the duplicate shows them

    render = scene.render
    render.engine = "CYCLES"
    render.resolution_x, render.resolution_y = size
    render.resolution_percentage = 100
    render.image_settings.file_format = "PNG"
    scene.cycles.device = "CPU"
    scene.cycles.samples = samples
    scene.cycles.use_adaptive_sampling = True
    scene.cycles.use_denoising = True
    scene.cycles.max_bounces = 4
    lo, hi = frame_camera(bpy, scene, [result, pts])

    floor_mesh = bpy.data.meshes.new("Floor")
    s = 20 * width
    floor_mesh.from_pydata([(-s, -s, 0), (s, -s, 0), (s, s, 0), (-s, s, 0)], [], [(0, 1, 2, 3)])
    floor = bpy.data.objects.new("Floor", floor_mesh)
    floor.location.z = lo.z
    floor.data.materials.append(material(bpy, "Floor", (0.82, 0.82, 0.80), 0.8))
    scene.collection.objects.link(floor)

    sun = bpy.data.objects.new("Sun", bpy.data.lights.new("Sun", "SUN"))
    sun.data.energy = 3.0
    sun.data.angle = math.radians(8)
    sun.rotation_euler = (math.radians(40), math.radians(15), math.radians(30))
    scene.collection.objects.link(sun)
    world = bpy.data.worlds.new("World")
    if world.node_tree is None:
        world.use_nodes = True
    bg = world.node_tree.nodes.get("Background")
    bg.inputs["Color"].default_value = (0.75, 0.80, 0.88, 1.0)
    bg.inputs["Strength"].default_value = 0.8
    scene.world = world


def main(argv=None) -> int:
    args = parse_args(argv)
    out = args.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    size = tuple(int(v) for v in args.size.lower().split("x"))
    if not args.input.is_file():
        sys.exit(f"input point cloud not found: {args.input}")
    # Blender's user folders (extensions, preferences) go under OUT, never into ~/.config/blender.
    os.environ["BLENDER_USER_RESOURCES"] = str(out / "blender-user")

    t0 = time.perf_counter()
    zip_path = args.zip.resolve() if args.zip else build_zip(out)
    import bpy

    bpy.ops.wm.read_homefile(use_empty=True)
    res = bpy.ops.extensions.package_install_files(
        filepath=str(zip_path), repo="user_default", enable_on_install=True, overwrite=True
    )
    if res != {"FINISHED"} or EXTENSION not in bpy.context.preferences.addons:
        sys.exit(f"installing {zip_path} failed")
    print(f"installed and enabled {zip_path.name} as {EXTENSION}")

    bpy.ops.wm.read_homefile(use_empty=True)
    scene = bpy.context.scene
    # The sample comes from an OBJ (Y up, -Z forward): convert to Blender's Z up. The importer puts
    # the rotation into the object's matrix, so the source has a non-identity world transform.
    bpy.ops.wm.ply_import(filepath=str(args.input), forward_axis=args.forward, up_axis=args.up)
    source = bpy.context.active_object
    print(f"imported {args.input.name}: {len(source.data.vertices):,} points")

    props = bpy.ops.object.nkf_reconstruct.get_rna_type().properties
    method = props["method"].default if args.method == "default" else args.method
    t1 = time.perf_counter()
    bpy.ops.object.nkf_reconstruct(method=method, resolution=args.resolution)
    t_rec = time.perf_counter() - t1
    result = bpy.context.active_object
    if result is None or result == source:
        sys.exit("the reconstruction produced no object")
    print(f"reconstructed '{result.name}' with {method}: {len(result.data.polygons):,} triangles in {t_rec:.1f} s")

    mesh_path = out / "sample_nkf_mesh.ply"
    for o in bpy.context.view_layer.objects.selected:
        o.select_set(False)
    result.select_set(True)
    bpy.ops.wm.ply_export(filepath=str(mesh_path), export_selected_objects=True, export_normals=True,
                          export_uv=False, export_colors="NONE", ascii_format=False)

    stage_scene(bpy, scene, source, result, args.samples, size)
    png = out / "sample_render.png"
    scene.render.filepath = str(png)
    t2 = time.perf_counter()
    bpy.ops.render.render(write_still=True)
    t_render = time.perf_counter() - t2
    blend = out / "sample_nkf.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    print(f"rendered {png} ({size[0]}x{size[1]}, {args.samples} samples, Cycles CPU) in {t_render:.1f} s")
    print(f"wrote {blend}")
    print(f"wrote {mesh_path}")
    print(f"main job done in {time.perf_counter() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
