"""``nkf_model.fit`` (the function) stays callable after the ``nkf_model.fit`` subpackage is imported,
whatever the order (a Blender user's first run imported the pipeline first and got "'module' object
is not callable")."""

import subprocess
import sys

import pytest

ORDERS = [
    "import nkf_model.pipeline.reconstruct",
    "import nkf_model.fit.augment",
    "nkf_model.reconstruct",
    "nkf_model.fit; import nkf_model.fit.solve",
]


@pytest.mark.parametrize("first", ORDERS)
def test_fit_is_the_function_in_any_import_order(first):
    code = (f"import nkf_model\n{first}\nfrom nkf_model.fit.augment import augment\nfrom nkf_model.fit import solve\n"
            "assert callable(nkf_model.fit) and nkf_model.fit.__module__ == 'nkf_model.pipeline.reconstruct'\n"
            "assert callable(augment) and callable(solve.solve_dense)\nprint('ok')")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0 and run.stdout.strip() == "ok", run.stderr
