"""service.core.numeric: the machine-independent replacements of numpy's CPU-dispatched
functions agree with the C library bit for bit and with numpy's linear algebra to rounding; and
a drive gives the same bits under every CPU this machine can emulate (numpy's SIMD dispatch and
OpenBLAS's kernels switched by environment), which is what made two machines disagree."""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from service.core import numeric

REPO = Path(__file__).resolve().parents[3]


def test_transcendental_functions_equal_the_c_library_bit_for_bit() -> None:
    rng = np.random.default_rng(3)
    y, x = rng.normal(size=5000) * 10, rng.normal(size=5000) * 10
    z = rng.normal(size=5000) * 30
    special = np.array([0.0, -0.0, np.inf, -np.inf, 1e-300, -1e-300, 700.0, 710.0, -750.0])
    got = numeric.atan2(y, x)
    assert (
        got.tobytes() == np.array([math.atan2(a, b) for a, b in zip(y, x, strict=True)]).tobytes()
    )
    for v in special:
        assert numeric.atan2(np.array([v]), np.array([1.0]))[0] == math.atan2(v, 1.0)
        assert numeric.atan2(v, -1.0) == math.atan2(v, -1.0)
    assert numeric.exp(z).tobytes() == np.array([math.exp(v) for v in z]).tobytes()
    assert numeric.exp(710.0) == math.inf and numeric.exp(np.array([710.0]))[0] == math.inf
    assert numeric.tanh(z).tobytes() == np.array([math.tanh(v) for v in z]).tobytes()
    pos = np.abs(z) + 1e-9
    assert numeric.log(pos).tobytes() == np.array([math.log(v) for v in pos]).tobytes()
    assert numeric.log(0.0) == -math.inf and math.isnan(numeric.log(-1.0))
    # shapes broadcast like numpy's
    assert numeric.atan2(np.ones((2, 3)), np.ones(3)).shape == (2, 3)
    assert numeric.exp(np.zeros((4, 2))).shape == (4, 2)


def test_products_and_small_solves_agree_with_numpy_to_rounding() -> None:
    rng = np.random.default_rng(4)
    a, b, v = rng.normal(size=(50, 3)), rng.normal(size=(3, 4)), rng.normal(size=3)
    assert np.allclose(numeric.matmul(a, b), a @ b, rtol=0, atol=1e-12)
    assert np.allclose(numeric.matvec(a, v), a @ v, rtol=0, atol=1e-12)
    assert math.isclose(numeric.dot(a[:, 0], a[:, 1]), float(a[:, 0] @ a[:, 1]), abs_tol=1e-12)
    m = rng.normal(size=(3, 3))
    assert math.isclose(numeric.quadratic(v, m), float(v @ m @ v), abs_tol=1e-12)
    for n in (2, 3, 5):
        A = rng.normal(size=(n, n)) + n * np.eye(n)
        rhs = rng.normal(size=n)
        assert np.allclose(numeric.solve(A, rhs), np.linalg.solve(A, rhs), rtol=1e-12, atol=0)
        assert np.allclose(numeric.inv(A), np.linalg.inv(A), rtol=1e-12, atol=1e-14)
    stack = rng.normal(size=(7, 3, 3)) + 3 * np.eye(3)
    rhs = rng.normal(size=(7, 3))
    assert np.allclose(numeric.solve(stack, rhs), np.linalg.solve(stack, rhs[..., None])[..., 0])
    with pytest.raises(np.linalg.LinAlgError):
        numeric.solve(np.zeros((3, 3)), np.ones(3))
    with pytest.raises(np.linalg.LinAlgError):
        numeric.inv(np.array([[1.0, 2.0], [2.0, 4.0]]))
    for m3 in (m, stack[0], np.diag([4.0, 0.25, 0.01])):
        assert math.isclose(numeric.det3(m3), float(np.linalg.det(m3)), rel_tol=1e-12)
    assert numeric.det3(np.array([[1.0, 2.0, 3.0], [2.0, 4.0, 6.0], [0.0, 1.0, 5.0]])) == 0.0


@pytest.mark.parametrize(
    "m",
    [
        [[2.0, 0.5], [0.5, 1.0]],
        [[1.0, 0.0], [0.0, 3.0]],
        [[3.0, 0.0], [0.0, 1.0]],
        [[1, 1], [1, 1]],
    ],
)
def test_the_closed_form_eigen_decomposition_of_a_symmetric_2x2(m: list) -> None:
    a = np.asarray(m, dtype=np.float64)
    vals, vecs = numeric.eigh_sym2(a)
    ref_vals, ref_vecs = np.linalg.eigh(a)
    assert np.allclose(vals, ref_vals, atol=1e-12)
    for k in range(2):  # the same directions, up to sign
        assert math.isclose(abs(float(vecs[:, k] @ ref_vecs[:, k])), 1.0, abs_tol=1e-12)
        assert np.allclose(a @ vecs[:, k], vals[k] * vecs[:, k], atol=1e-12)


# A budgeted global search on a generated floor plan (the most sensitive path: it decides
# between near-equal places), then shape, ICP and line-based tracking on the office: every pose
# and covariance hashed.
_WORKLOAD = """
import hashlib
import numpy as np
from service.core.factory import create_localizer
from sim_publisher.generator import BuildingParams, generate_building
from sim_publisher.scenario import building_setup, make_setup

h = hashlib.sha256()
def add(a):
    h.update(np.ascontiguousarray(np.asarray(a, dtype=np.float64)).tobytes())
su = building_setup(generate_building(65, BuildingParams(people=0)), 2, seed=0)
add(su.scan(40)[0])
loc = create_localizer("shape", su.map_data, None, search_budget_ms=50.0)
for i in range(29, 90):
    est = loc.update(*su.scan(i), su.odom[i])
    add(est.pose)
    h.update(est.status.encode())
office = make_setup(1)
for method in ("shape", "icp", "lines"):
    loc = create_localizer(method, office.map_data, office.truth[0])
    for i in range(1, 30 if method == "shape" else 12):
        est = loc.update(*office.scan(i), None)
        add(est.pose)
        if est.covariance is not None:
            add(est.covariance)
print(h.hexdigest())
"""

#: Environments that make numpy and OpenBLAS behave as on other x86-64 CPUs: numpy without its
#: AVX-512 paths (as on a CPU without AVX-512), without AVX2 too, and OpenBLAS's Haswell and
#: generic kernels instead of the ones it picks for this CPU.
_CPUS = {
    "no AVX-512 in numpy": {"NPY_DISABLE_CPU_FEATURES": "X86_V4 AVX512_ICL AVX512_SPR"},
    "baseline numpy, generic BLAS": {
        "NPY_DISABLE_CPU_FEATURES": "X86_V3 X86_V4 AVX512_ICL AVX512_SPR",
        "OPENBLAS_CORETYPE": "Prescott",
    },
    "Haswell BLAS": {"OPENBLAS_CORETYPE": "Haswell"},
}


def _workload_hash(extra: dict[str, str]) -> str:
    env = {k: v for k, v in os.environ.items() if k not in ("NPY_DISABLE_CPU_FEATURES",)}
    env.pop("OPENBLAS_CORETYPE", None)
    env.update(extra)
    out = subprocess.run(
        [sys.executable, "-c", _WORKLOAD],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=240,
        check=True,
    )
    return out.stdout.strip().splitlines()[-1]


@pytest.mark.slow
def test_a_drive_gives_the_same_bits_on_every_emulated_cpu() -> None:
    """Before the core used :mod:`service.core.numeric`, this drive's poses differed between
    these environments (and the first fix of two drive-search tests moved by ~40 scans)."""
    here = _workload_hash({})
    for name, extra in _CPUS.items():
        assert _workload_hash(extra) == here, name


def test_numba_does_not_vectorise_the_c_library_calls() -> None:
    """With Intel's SVML installed numba would vectorise the elementwise loops with its own
    (CPU-dependent) functions; the bit-for-bit equality above relies on it not doing so."""
    numba = pytest.importorskip("numba")
    assert not numba.config.USING_SVML
