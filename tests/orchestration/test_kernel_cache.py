"""A worker loads the kernels numba has cached, and compiles none (issue 16, kernel_cache)."""

import os
import subprocess
import sys

from forestmap_assets.orchestration.kernel_cache import kernel_modules

LOAD = """
from forestmap_assets.core import _cloud_kernels as k
from forestmap_assets.orchestration.kernel_cache import load_cached_kernels
print(load_cached_kernels(), len(k.bounds.signatures), len(k.voxel_numbers.signatures))
"""


def test_every_kernel_module_is_listed():
    names = kernel_modules()
    assert "forestmap_assets.io._projection_kernels" in names
    assert "forestmap_assets.core.registration._score_bound_kernels" in names
    assert all(n.rsplit(".", 1)[-1].endswith("_kernels") for n in names)


def test_only_cached_signatures_are_loaded(tmp_path):
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path))  # an empty cache of this test's own
    compile_one = "import numpy as np; from forestmap_assets.core import _cloud_kernels as k; k.bounds(np.zeros((3, 3)))"
    subprocess.run([sys.executable, "-c", compile_one], env=env, check=True)
    out = subprocess.run([sys.executable, "-c", LOAD], env=env, check=True, capture_output=True, text=True)
    loaded, corner, numbers = (int(v) for v in out.stdout.split())
    assert (loaded, corner, numbers) == (1, 1, 0)  # the one cached signature; nothing compiled
