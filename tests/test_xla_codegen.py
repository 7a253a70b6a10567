"""The tests compile with XLA's fusion emitters and LLVM's optimisation
passes off, and each program's code generated in one piece, where XLA
allows it (conftest.py: the many small programs then compile sooner).
Here the same programs compiled with XLA's defaults, in a subprocess with
XLA_FLAGS empty, agree with this process's to round-off, so what the
other tests check holds for the defaults too."""

import numpy as np

from helpers import codegen_probe, run_under_default_codegen

_SCRIPT = """
import sys
import jax
import numpy as np
jax.config.update("jax_enable_x64", True)
from helpers import codegen_probe
np.savez(sys.argv[1], **codegen_probe())
"""


def test_default_code_generator_agrees_to_round_off(tmp_path):
    out = tmp_path / "default.npz"
    run_under_default_codegen(_SCRIPT, str(out))
    default = np.load(out)
    here = codegen_probe()
    assert sorted(default.files) == sorted(here)
    for name, value in here.items():
        scale = np.max(np.abs(value))
        assert scale > 1e-3, name  # values of size, so that the comparison means something
        assert np.max(np.abs(value - default[name])) <= 1e-12 * scale, name
