"""The options object: one place for every setting's default, range and message; reconstruct,
estimate and the command line take it; ``import nkf_model`` loads nothing heavy."""

import subprocess
import sys

import numpy as np
import pytest
from shapes import sphere_points

import nkf_model
from nkf_model.errors import InvalidParameterError
from nkf_model.options import SETTING, SETTINGS, Options, scan_preset

HEAVY = ("torch", "numba", "scipy", "skimage", "threadpoolctl", "nkf_model.pipeline.reconstruct")


def test_every_setting_is_a_field_with_its_default():
    opts = Options()
    assert [s.name for s in SETTINGS] == list(opts.as_dict())
    for s in SETTINGS:
        assert getattr(opts, s.name) == s.default, s.name
        if s.kind == "choice":
            assert s.default in s.values or (s.optional and s.default is None)


@pytest.mark.parametrize("changes, message", [
    (dict(resolution=8), "resolution must be between 16 and 1024"),
    (dict(resolution=64.5), "resolution must be an integer"),
    (dict(lam=-1.0), "lambda must be a finite number >= 0"),
    (dict(lam=float("nan")), "lambda must be a finite number >= 0"),
    (dict(lam="big"), "lambda must be a number"),
    (dict(method="poisson"), "method must be one of splines, nkf"),
    (dict(device="tpu"), "device must be"),
    (dict(eps=0.5), "eps must be in"),
    (dict(max_centres=10), "max_centres must be an integer >= 100"),
    (dict(reduce_to=5), "reduce_to must be an integer >= 1000 or None"),
    (dict(trim=0.0), "trim must be a positive number"),
    (dict(trim="far"), "trim must be a number"),
    (dict(min_piece=1.0), "min_piece must be a fraction"),
    (dict(solver="magic"), "solver must be one of auto, dense, falkon, pou"),
    (dict(normals_mode="maybe"), "normals_mode must be one of"),
    (dict(orientation="sideways"), "orientation must be one of outward, up, viewpoint"),
    (dict(max_points=3), "max_points must be an integer >= 10"),
    (dict(seed=-1), "seed must be an integer >= 0"),
    (dict(memory_budget=0), "memory_budget must be a positive number"),
])
def test_one_message_per_bad_setting(changes, message):
    with pytest.raises(InvalidParameterError, match=message):
        Options(**changes)
    with pytest.raises(InvalidParameterError, match=message):
        Options().replace(**changes)


def test_numpy_scalars_and_numeric_lambda_strings_are_taken():
    opts = Options(resolution=np.int64(64), lam="1e-8", min_piece=np.float32(0.01))
    assert opts.resolution == 64 and type(opts.resolution) is int
    assert opts.lam == 1e-8


def test_build_rejects_unknown_settings_and_other_objects():
    with pytest.raises(InvalidParameterError, match="unknown setting resolutoin"):
        Options.build(resolutoin=64)
    with pytest.raises(InvalidParameterError, match="options must be an nkf_model.Options"):
        Options.build({"resolution": 64})
    base = Options(resolution=64)
    assert Options.build(base) is base
    assert Options.build(base, lam=1e-6) == Options(resolution=64, lam=1e-6)
    assert scan_preset().scan and not Options().scan


def test_reconstruct_with_options_equals_keywords():
    pts, nrm = sphere_points(400, seed=3)
    a = nkf_model.reconstruct(pts, nrm, method="splines", resolution=32, lam=1e-8)
    b = nkf_model.reconstruct(pts, nrm, options=Options(method="splines", resolution=32, lam=1e-8))
    c = nkf_model.reconstruct(pts, nrm, options=Options(method="splines", resolution=48), resolution=32, lam=1e-8)
    for m in (b, c):
        np.testing.assert_array_equal(a.vertices, m.vertices)
        np.testing.assert_array_equal(a.faces, m.faces)
    with pytest.raises(InvalidParameterError, match="unknown setting"):
        nkf_model.reconstruct(pts, nrm, method="splines", resolutoin=32)


def test_max_points_subset_is_seeded_and_reported():
    pts, nrm = sphere_points(800, seed=4)
    m = nkf_model.reconstruct(pts, nrm, method="splines", resolution=32, max_points=300, seed=5)
    assert m.stats["subset"] == {"from": 800, "to": 300}
    assert m.stats["points_used"] == 300 and m.stats["points_in"] == 800
    keep = np.sort(np.random.default_rng(5).choice(800, 300, replace=False))
    ref = nkf_model.reconstruct(pts[keep], nrm[keep], method="splines", resolution=32, seed=5)
    np.testing.assert_array_equal(ref.vertices, m.vertices)
    assert nkf_model.reconstruct(pts, nrm, method="splines", resolution=32).stats["subset"] is None


def test_estimate_uses_the_same_defaults_as_reconstruct():
    assert nkf_model.estimate(5000) == nkf_model.estimate(5000, options=Options())
    e = nkf_model.estimate(5000, method="splines", max_points=1000)
    assert e.points_in == 1000 and e.solver == "dense"
    assert nkf_model.estimate(5000, method=SETTING["method"].default) == nkf_model.estimate(5000)


def _imported_after(code: str) -> list[str]:
    probe = f"import sys\n{code}\nprint(','.join(m for m in {HEAVY!r} if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True).stdout
    return [m for m in out.strip().split(",") if m]


def test_importing_the_package_and_its_settings_loads_nothing_heavy():
    assert _imported_after("import nkf_model, nkf_model.options, nkf_model.pipeline.stages") == []
    assert _imported_after("import nkf_model; nkf_model.Options(resolution=64); nkf_model.METHODS") == []
    # the first use of the reconstruction loads it
    assert "nkf_model.pipeline.reconstruct" in _imported_after("import nkf_model; nkf_model.reconstruct")


def test_estimate_normals_takes_the_cancel_poll_under_its_old_name_too():
    from nkf_model.errors import Cancelled

    pts, _ = sphere_points(300, seed=1)

    def stop():
        raise Cancelled("stop")

    for kw in ("cancel_poll", "check"):
        with pytest.raises(Cancelled):
            nkf_model.estimate_normals(pts, **{kw: stop})
