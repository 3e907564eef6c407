"""A mesh partitioned into k-d blocks, rendered and differentiated by Ray
workers and composited sort-last, is the whole mesh rendered in one process
(``mi.render``, the same sampler, film and filter): the image within 1e-5 per
pixel and the gradients within 1e-4 of their largest, with rays along a
plane between blocks, the camera inside the mesh, a post-classified scalar
and a floor lit by an emitter (Mitsuba's own ``prb`` behind the volume).
VTK opens the ``.pvtu`` as the mesh once over (its ghost cells dropped)."""
from __future__ import annotations

import os

import numpy as np
import pytest

ray = pytest.importorskip("ray")

RES = (33, 25)          # odd width: a column of rays through the image's centre


@pytest.fixture(scope="module")
def cluster():
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield
    ray.shutdown()


@pytest.fixture(scope="module")
def mesh():
    from mi_tetvr.mesh.generate import blob_field, grid_mesh
    V, T = grid_mesh((7, 6, 5), jitter=0.2, seed=3)
    color, opacity = blob_field(V, scale=6.0)
    scalar = opacity / opacity.max() + 0.3 * V[:, 0]
    return V, T, color, opacity, scalar


@pytest.fixture(scope="module")
def partitions(mesh, tmp_path_factory):
    from mi_tetvr.mesh.partition import partition_mesh
    V, T, color, opacity, scalar = mesh
    root = tmp_path_factory.mktemp("blocks")
    return {n: partition_mesh(V, T, root / f"m{n}.pvtu", n,
                              {"color": color, "opacity": opacity, "scalar": scalar})
            for n in (2, 4, 8)}


def scene_dict(origin, target, floor=False, mesh=None):
    import mitsuba as mi
    from mi_tetvr.camera import look_at
    d = {"type": "scene", "integrator": {"type": "tetvr", "min_transmittance": 0.0},
         "sensor": {"type": "perspective", "fov": 60,
                    "to_world": mi.ScalarTransform4f(look_at(origin, target, (0, 0, 1))),
                    "film": {"type": "hdrfilm", "width": RES[0], "height": RES[1],
                             "rfilter": {"type": "gaussian"}},
                    "sampler": {"type": "stratified", "sample_count": 1, "jitter": False}}}
    if floor:
        d["floor"] = {"type": "rectangle", "bsdf": {"type": "diffuse"},
                      "to_world": mi.ScalarTransform4f().translate([0, 0, -1.3]).scale(3.0)}
        d["sky"] = {"type": "constant", "radiance": {"type": "rgb", "value": [0.4, 0.5, 0.6]}}
    if mesh is not None:
        d["mesh"] = mesh
    return d


def shape_of(mesh, scalar):
    """The tetmesh properties of the blocks, and the whole mesh's shape."""
    import mi_tetvr
    V, T, color, opacity, field = mesh
    if scalar:
        props = {"transfer_function": "viridis", "opacity_scale": 4.0}
        rng = {"value_min": float(field.min()), "value_max": float(field.max())}
        return ({**props, "scalar_attribute": "scalar"},
                mi_tetvr.tetmesh_dict(V, T, scalar=field, **props, **rng))
    return {}, mi_tetvr.tetmesh_dict(V, T, color, opacity)


def split_plane(part):
    """``(axis, value)`` of the first k-d split (shared by 2, 4 and 8 blocks)."""
    box = part.boxes()[0]
    axis = int(np.flatnonzero(np.isfinite(box[1]))[0])
    return axis, float(box[1, axis])


def views(partitions):
    """Three cameras: on the first split plane looking along it, inside the
    mesh, and above it with a floor."""
    axis, s = split_plane(partitions[2])
    origin = np.zeros(3)
    origin[axis] = s
    other = (axis + 1) % 3 if (axis + 1) % 3 != 2 else (axis + 2) % 3
    origin[other] = -3.0
    target = origin.copy()
    target[other] = 0.0
    return {"along the split plane": (origin, target, False),
            "inside": ((0.1, -0.05, 0.05), (1.0, 0.4, 0.3), False),
            "floor": ((2.2, -2.6, 1.6), (0.0, 0.0, -0.4), True)}


def test_partition_is_the_mesh_once_over(mesh, partitions):
    """Each block's piece holds every tet with a corner in its box and owns
    those whose centroid it holds, the boxes tile space; VTK reads the ``.pvtu`` (the reference),
    and without its duplicate cells it is the mesh; the pieces joined again
    by their global ids are the mesh exactly."""
    import pyvista as pv
    from mi_tetvr.mesh.partition import GHOST, assemble, read_piece
    V, T, color, opacity, scalar = mesh
    for n, part in partitions.items():
        boxes = part.boxes()
        assert len(boxes) == n
        centroids = V[T].mean(1)
        inside = np.zeros(len(T), int)
        for box in boxes:
            inside += np.all(centroids >= box[0], 1) & np.all(centroids < box[1], 1)
        assert np.all(inside == 1)                      # the boxes tile the centroids' space
        for k, (lo, hi) in enumerate(boxes):
            _, _, _, _, _, (cells, own) = read_piece(part, k, ghosts=True)
            # every tet with a corner inside the box is there; it owns those whose
            # centroid it holds
            corner_in = np.all((V > lo) & (V < hi), 1)[T].any(1)
            assert np.isin(np.flatnonzero(corner_in), cells).all()
            held = np.all((centroids >= lo) & (centroids < hi), 1)
            assert np.array_equal(np.sort(cells[own]), np.flatnonzero(held))
        grid = pv.read(part.path)
        assert grid.n_cells == sum(b.tets for b in part.blocks)
        kept = grid.extract_cells(np.flatnonzero(grid.cell_data[GHOST] == 0))
        assert kept.n_cells == len(T)
        got = np.sort(np.sort(kept.points[kept.cells_dict[pv.CellType.TETRA]].sum(1), 1), 0)
        want = np.sort(np.sort(V[T].sum(1), 1), 0)
        assert np.allclose(got, want, atol=1e-12)
        whole = assemble(part)
        assert np.array_equal(whole.points, V) and np.array_equal(whole.cells[0].data, T)
        assert np.array_equal(whole.point_data["scalar"], scalar)


def test_rays_along_a_block_face_are_in_one_block():
    from mi_tetvr.distributed import block_intervals
    inf = np.inf
    boxes = np.array([[[-inf, -inf, -inf], [0.5, inf, inf]],
                      [[0.5, -inf, -inf], [inf, inf, inf]]])
    o = np.array([[0.5, -3.0, 0.0], [0.2, -3.0, 0.0], [0.0, -3.0, 0.0]])
    d = np.array([[0.0, 1.0, 0.0], [0.0, 1.0, 0.0], [0.6, 0.8, 0.0]])
    iv = block_intervals(o, d, np.zeros(3), np.full(3, 10.0), boxes)
    live = iv[..., 1] > iv[..., 0]
    assert live.tolist() == [[False, True], [True, False], [True, True]]
    # a ray crossing the plane: the two intervals meet there
    assert iv[2, 0, 1] == iv[2, 1, 0] == pytest.approx(0.5 / 0.6)


@pytest.mark.parametrize("blocks", [2, 4, 8])
def test_blocks_render_the_whole_mesh(cluster, mesh, partitions, blocks):
    import mitsuba as mi
    from mi_tetvr.distributed import PartitionedMesh
    props, whole = shape_of(mesh, scalar=False)
    cams = views(partitions)
    # the camera on the plane: a column of its rays lies in the plane
    origin, target, _ = cams["along the split plane"]
    axis, s = split_plane(partitions[2])
    sensor = mi.load_dict(scene_dict(origin, target)["sensor"])
    ray, _ = sensor.sample_ray(0.0, 0.0, mi.Point2f([(16 + 0.5) / RES[0]] * 3, [0.2, 0.5, 0.8]),
                               mi.Point2f(0.5))
    assert np.all(np.array(ray.d)[axis] == 0.0) and np.all(np.array(ray.o)[axis] == s)
    with PartitionedMesh(partitions[blocks].path, workers=2, shape=props) as pm:
        for name, (o, t, floor) in cams.items():
            want = np.array(mi.render(mi.load_dict(scene_dict(o, t, floor, whole))))
            got = np.array(pm.render(mi.load_dict(scene_dict(o, t, floor))))
            assert want[..., :3].max() > 0.05, name
            assert np.abs(got - want).max() < 1e-5, (name, np.abs(got - want).max())


def test_post_classified_scalar_in_blocks(cluster, mesh, partitions):
    """The blocks map the scalar over the whole mesh's range (each piece's
    own range differs) and classify it along the rays as one mesh does."""
    import mitsuba as mi
    from mi_tetvr.distributed import PartitionedMesh
    props, whole = shape_of(mesh, scalar=True)
    o, t, _ = views(partitions)["floor"]
    with PartitionedMesh(partitions[4].path, workers=2, shape=props) as pm:
        want = np.array(mi.render(mi.load_dict(scene_dict(o, t, True, whole))))
        got = np.array(pm.render(mi.load_dict(scene_dict(o, t, True))))
    assert want[..., :3].max() > 0.05
    assert np.abs(got - want).max() < 1e-5


def test_view_dependent_colors_in_blocks(cluster, mesh, tmp_path):
    """Blocks whose pieces carry spherical harmonics (point data ``sh``) render as
    the whole view-dependent mesh does."""
    import mitsuba as mi

    import mi_tetvr
    from mi_tetvr.distributed import PartitionedMesh
    from mi_tetvr.mesh.partition import partition_mesh
    V, T, color, opacity, _ = mesh
    sh = np.random.default_rng(8).normal(scale=0.4, size=(len(V), 4, 3))
    part = partition_mesh(V, T, tmp_path / "sh.pvtu", 4,
                          {"opacity": opacity, "sh": sh.reshape(len(V), -1)})
    whole = mi_tetvr.tetmesh_dict(V, T, opacity=opacity, sh=sh)
    o, t, _ = views({2: part})["floor"]
    with PartitionedMesh(part.path, workers=2) as pm:
        want = np.array(mi.render(mi.load_dict(scene_dict(o, t, True, whole))))
        got = np.array(pm.render(mi.load_dict(scene_dict(o, t, True))))
    assert want[..., :3].max() > 0.05
    assert np.abs(got - want).max() < 1e-5


@pytest.mark.parametrize("scalar", [False, True], ids=["colors", "scalar"])
def test_gradients_across_blocks(cluster, mesh, partitions, scalar):
    """``dr.backward`` of one process and the blocks' adjoints summed over the
    vertices they share: colors, opacities and positions (a scalar mesh: its
    scalar, positions and the transfer function's texels)."""
    import drjit as dr
    import mitsuba as mi
    from mi_tetvr.distributed import PartitionedMesh
    props, whole = shape_of(mesh, scalar)
    o, t, _ = views(partitions)["floor"]
    weights = np.random.default_rng(0).normal(size=(RES[1], RES[0], 4)).astype(np.float32)
    with PartitionedMesh(partitions[4].path, workers=2, shape=props) as pm:
        got = pm.backward(mi.load_dict(scene_dict(o, t, True)), weights)
    scene = mi.load_dict(scene_dict(o, t, True, whole))
    params = mi.traverse(scene)
    names = (["vertex_scalar", "vertex_positions", "tf_color", "tf_opacity"] if scalar
             else ["vertex_color", "vertex_opacity", "vertex_positions"])
    for n in names:
        dr.enable_grad(params[f"mesh.{n}"])
    params.update()
    img = mi.render(scene, params)
    dr.backward(dr.sum(img * mi.TensorXf(weights), axis=None))
    n_vertices = len(mesh[0])
    for n in names:
        want = np.array(dr.grad(params[f"mesh.{n}"]), np.float64)
        have = got[n]
        if n.startswith("vertex_"):
            want = want.reshape(n_vertices, -1)
        else:
            have = have.reshape(want.shape)
        scale = np.abs(want).max()
        assert scale > 0, n
        assert np.abs(have - want).max() < 1e-4 * scale, (n, np.abs(have - want).max() / scale)


def test_bad_partitions_and_dead_workers(cluster, mesh, partitions, tmp_path):
    import shutil

    import mitsuba as mi
    from mi_tetvr.distributed import PartitionedMesh
    from mi_tetvr.mesh.partition import MeshError, blocks_path, read_partition
    part = partitions[2]
    # a missing piece
    copy = tmp_path / "c.pvtu"
    shutil.copy(part.path, copy)
    shutil.copy(blocks_path(part.path), blocks_path(copy))
    shutil.copytree(part.path.parent / part.path.stem, tmp_path / "c")
    for f in (tmp_path / "c").iterdir():
        f.rename(f.with_name(f.name.replace(part.path.stem + "_", "c_")))
    (tmp_path / "c" / "c_1.vtu").unlink()
    text = copy.read_text().replace(f"{part.path.stem}/{part.path.stem}_", "c/c_")
    copy.write_text(text)
    side = blocks_path(copy)
    side.write_text(side.read_text().replace(f"{part.path.stem}/{part.path.stem}_", "c/c_"))
    with pytest.raises(FileNotFoundError, match=r"1 of 2 pieces missing: .*c_1\.vtu"):
        read_partition(copy)
    # a .pvtu of unknown boxes
    blocks_path(copy).unlink()
    with pytest.raises(MeshError, match="blocks' boxes are unknown"):
        read_partition(copy)
    # a worker that dies between two renders is started again (its piece read anew);
    # with no retries left the render fails with a message
    o, t, _ = views(partitions)["inside"]
    scene = mi.load_dict(scene_dict(o, t))
    for retries in (1, 0):
        with PartitionedMesh(part.path, workers=2, retries=retries) as pm:
            first = np.array(pm.render(scene))
            pid = ray.get(pm.actors[1].pid.remote())
            os.kill(pid, 9)
            if retries:
                assert np.abs(np.array(pm.render(scene)) - first).max() < 1e-6
            else:
                with pytest.raises(RuntimeError, match="worker of block 1 .* died"):
                    pm.render(scene)


def test_an_address_no_cluster_answers_is_a_clear_error(partitions):
    import socket
    import subprocess
    import sys
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]            # (closed again: nothing listens there)
    r = subprocess.run([sys.executable, "-m", "mi_tetvr.cli", "render",
                        str(partitions[2].path), "--workers", "2", "--address",
                        f"127.0.0.1:{port}", "-o", str(partitions[2].path.with_suffix(".png"))],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 1
    assert f"no Ray cluster answers at '127.0.0.1:{port}'" in r.stderr
    assert not partitions[2].path.with_suffix(".png").exists()


def test_adam_over_blocks_is_adam_on_the_whole_mesh(cluster, mesh, partitions):
    """Three Adam steps on colors and opacities towards an image: each block
    steps its vertices with the gradients summed over the blocks (so the
    copies of a shared vertex stay equal), as Mitsuba's Adam steps the whole
    mesh in one process."""
    import drjit as dr
    import mitsuba as mi
    from mi_tetvr.distributed import PartitionedMesh
    props, whole = shape_of(mesh, scalar=False)
    o, t, _ = views(partitions)["inside"]
    lr = {"vertex_color": 0.05, "vertex_opacity": 0.2}
    target = np.zeros((RES[1], RES[0], 4), np.float32)
    target[..., :3] = 0.3
    scene = mi.load_dict(scene_dict(o, t))
    with PartitionedMesh(partitions[4].path, workers=2, shape=props) as pm:
        pm.optimizer(lr)
        for _ in range(3):
            img = np.array(pm.render(scene))
            pm.step(pm.backward(scene, 2 * (img - target) / img.size))
        got = pm.arrays(lr)
    one = mi.load_dict(scene_dict(o, t, mesh=whole))
    params = mi.traverse(one)
    opt = mi.ad.Adam(lr=1.0, params={f"mesh.{n}": params[f"mesh.{n}"] for n in lr})
    opt.set_learning_rate({f"mesh.{n}": v for n, v in lr.items()})
    start = {n: np.array(params[f"mesh.{n}"]).reshape(len(mesh[0]), -1) for n in lr}
    for _ in range(3):
        params.update(opt)
        img = mi.render(one, params)
        dr.backward(dr.sum(dr.square(img - mi.TensorXf(target)), axis=None) / dr.width(img))
        opt.step()
    params.update(opt)
    for n in lr:
        want = np.array(params[f"mesh.{n}"]).reshape(len(mesh[0]), -1)
        moved = np.abs(want - start[n]).max(1) > 0
        assert moved.sum() > 50, n
        assert np.abs(got[n] - want).max() < 1e-4, (n, np.abs(got[n] - want).max())


def test_fit_over_blocks_writes_the_mesh_it_scores(cluster, tiny_data_path, tmp_path):
    """``fit --workers``: the loss falls, and the mesh it writes (its pieces,
    each written by its worker), read whole and rendered in one process,
    scores the held-out PSNR the fit reports."""
    import json

    import mitsuba as mi

    import mi_tetvr
    from mi_tetvr import read_tetmesh
    from mi_tetvr.cli import main
    from mi_tetvr.mesh.generate import grid_mesh
    from mi_tetvr.mesh.partition import partition_mesh
    from mi_tetvr.recon.datasets import load_nerf
    from mi_tetvr.recon.metrics import image_metrics
    data = tiny_data_path
    V, T = grid_mesh(6)
    partition_mesh(V, T, tmp_path / "init.pvtu", 3,
                   {"color": np.full((len(V), 3), 0.5), "opacity": np.full(len(V), 1.0)})
    main(["fit", str(data), "-o", str(tmp_path / "fit"), "--init", str(tmp_path / "init.pvtu"),
          "--workers", "2", "--iterations", "8", "--lr-color", "0.05", "--quiet"])
    m = json.loads((tmp_path / "fit" / "metrics.json").read_text())
    assert m["step"] == 8 and np.mean(m["losses"][-3:]) < np.mean(m["losses"][:3])
    whole = read_tetmesh(tmp_path / "fit" / "mesh.pvtu")
    assert not np.allclose(whole.color, 0.5)
    d = load_nerf(data)
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "tetvr"},
                          "mesh": mi_tetvr.tetmesh_dict(
                              whole.vertices, whole.tets, whole.color, whole.opacity)})
    for view in d.test:
        img = np.array(mi.render(scene, sensor=mi.load_dict(view.camera.sensor_dict())))
        got = image_metrics(img, view.image, None)["psnr"]
        assert got == pytest.approx(m["views"][view.name]["psnr"], abs=1e-3)


def test_a_series_over_workers_is_the_series_rendered_here(cluster, mesh, tmp_path):
    """``render MESH MESH ... --workers 2``: the frames Ray workers render (each
    keeping its kernels) are the frames of the loop in this process."""
    import mitsuba as mi
    from mi_tetvr.cli import main
    from mi_tetvr.mesh import TetMesh, write_tetmesh
    V, T, color, opacity, _ = mesh
    paths = []
    for k in range(3):
        paths.append(str(tmp_path / f"m{k}.vtu"))
        write_tetmesh(paths[-1], TetMesh(V, T, np.roll(color, k, axis=1), opacity * (1 + k)))
    for name, extra in (("here", []), ("workers", ["--workers", "2"])):
        main(["render", *paths, "-o", str(tmp_path / f"{name}.exr"), "--res", "24x16", *extra])
    for k in range(3):
        here = np.array(mi.Bitmap(str(tmp_path / f"here_{k:04d}.exr")))
        there = np.array(mi.Bitmap(str(tmp_path / f"workers_{k:04d}.exr")))
        assert here[..., :3].max() > 0.05
        assert np.abs(here - there).max() < 1e-6
