"""``nkf reconstruct`` as a program does no work beyond the reconstruction it does not need
(issue 20, "Command line start"; the measurements are in docs/blender-user.md): no PyTorch on the
CPU path, no SciPy graph module unless normals are estimated or a mesh is trimmed, no garbage
collection while the solver's modules load, none over the whole heap at shutdown; and an
in-process caller of ``main([...])`` keeps its garbage collector as it was."""

from __future__ import annotations

import gc
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from shapes import sphere_points

from nkf_model.cli import main
from nkf_model.io.files import read_mesh, write_point_cloud
from nkf_model.kernel import engines

PROGRAM = textwrap.dedent(
    """
    import gc, sys
    sys.argv = ["nkf", "reconstruct", *sys.argv[1:]]
    import nkf_model.cli as cli
    COLLECTIONS_WHILE_LOADING = [None]
    load = cli._load_solver

    def counted(program):  # how many collections loading the solver sets off
        runs = []
        gc.callbacks.append(lambda phase, info: runs.append(1) if phase == "start" else None)
        try:
            return load(program)
        finally:
            gc.callbacks.clear()
            COLLECTIONS_WHILE_LOADING[0] = len(runs)

    cli._load_solver = counted
    rc = cli.main()
    print(rc, "torch" in sys.modules, "scipy.sparse.csgraph" in sys.modules, gc.isenabled(),
          gc.get_freeze_count() > 0, COLLECTIONS_WHILE_LOADING[0])
    """
)


@pytest.fixture(scope="module")
def cloud(tmp_path_factory):
    p, n = sphere_points(300, radius=1.5, seed=3)
    path = tmp_path_factory.mktemp("start") / "cloud.ply"
    write_point_cloud(path, p, n)
    return path


@pytest.mark.parametrize("method", ["splines", "nkf"])
def test_program_loads_only_what_the_method_needs_and_skips_the_exit_sweep(cloud, tmp_path, method):
    out = tmp_path / "program.ply"
    args = [str(cloud), str(out), "--method", method, "--resolution", "24", "--quiet"]
    run = subprocess.run([sys.executable, "-c", PROGRAM, *args], capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr
    rc, torch, csgraph, gc_enabled, frozen, collections = run.stdout.split()
    assert rc == "0"
    if not engines.cuda_driver_present():  # device "auto" looks for CUDA only where a driver is
        assert torch == "False"
    assert csgraph == "False"  # given normals, no trimming: no graph work, no graph module
    assert collections == "0"  # loading the solver: the collector paused
    assert (gc_enabled, frozen) == ("False", "True")  # main() as the program: its process ends next
    # ... and it writes what an in-process run writes: byte for byte, unless this process has PyTorch
    # loaded and NKF's feature net runs in it (kernel.weights.resolve_backend: "the same features
    # within 1e-6"), when the vertices agree to float32 rounding and the faces exactly.
    same = tmp_path / "in_process.ply"
    assert main(["reconstruct", str(cloud), str(same), *args[2:]]) == 0
    if method == "splines" or "torch" not in sys.modules:
        assert same.read_bytes() == out.read_bytes()
    else:
        a, b = read_mesh(out), read_mesh(same)
        assert np.array_equal(a[1], b[1])
        assert np.allclose(a[0], b[0], rtol=0, atol=1e-5)


def test_in_process_main_keeps_the_collector(cloud, tmp_path):
    frozen = gc.get_freeze_count()
    assert gc.isenabled()
    assert main(["reconstruct", str(cloud), str(tmp_path / "m.ply"), "--resolution", "24", "--quiet"]) == 0
    assert gc.isenabled()
    assert gc.get_freeze_count() == frozen
