"""The random-effect adjustment with each pass split over threads equals the one-part loop."""

from __future__ import annotations

import numpy as np
from helpers import F_TRUE, POSE, SIGMA
from test_mixed import COUNTS, EDGES, two_face_scan

from hartrao_jax.geometry._geometry import panel_cells
from hartrao_jax.model._model import make_model
from hartrao_jax.solver._mixed import gauss_helmert_mixed, mixed_threads


def test_split_passes_equal_one_part():
    """Two and three parts (padded tails, a cell cut between parts, robust rejection, ridge
    modes, variance components) give the one-part result to round-off."""
    names = ("tx", "ty", "tz", "rx", "ry", "f", "zern_5", "zern_6")
    model = make_model(list(names), aperture_radius_m=EDGES[-1])
    lobs, X = two_face_scan(3, n=9000, modes={6: 2e-4})
    lobs[::997, 0] += 0.01  # outliers for the robust rejection
    x0 = np.array([{**POSE, "f": F_TRUE}.get(k, 0.0) for k in model.free])
    cell, local, n_cells, _ = panel_cells(X, EDGES, COUNTS)
    design = np.column_stack([np.ones(len(X)), local]) * (cell >= 0)[:, None]
    ridge = {"astig": [model.free.index("zern_5"), model.free.index("zern_6")]}
    fits = [gauss_helmert_mixed(model, lobs, x0, SIGMA, np.zeros((len(lobs), 2)),
                                np.ones(len(lobs)), cell, design, n_cells,
                                cell_var0=np.array([1e-8, 1e-8, 1e-8]), ridge=ridge,
                                robust_k=4.0, threads=t, chunk_size=2048) for t in (1, 2, 3)]
    ref = fits[0]
    assert int(np.sum(np.asarray(ref.weights) == 0)) > 0
    for r in fits[1:]:
        assert int(r.iterations) == int(ref.iterations)
        assert bool(r.converged) == bool(ref.converged)
        np.testing.assert_array_equal(np.asarray(r.weights), np.asarray(ref.weights))
        for name in ("x", "cov", "u", "u_cov", "noise_var", "cell_var", "ridge_var", "sigma0",
                     "v", "normalized", "dev", "omega_point", "x_response", "ridge_fixed",
                     "ridge_fixed_cov", "redundancy_noise", "redundancy_cells"):
            a, b = np.asarray(getattr(r, name)), np.asarray(getattr(ref, name))
            # the per-point statistics come from the pass's terms kept in float32
            # (STORE_DTYPE): a last bit of a point's terms may round the other way
            rtol = 1e-6 if name in ("v", "normalized", "omega_point") else 1e-9
            np.testing.assert_allclose(a, b, rtol=rtol, atol=1e-9 * np.max(np.abs(b)),
                                       err_msg=name)


def test_parts_never_empty():
    """Four chunks asked for in three parts make two (a third would hold no point): the
    one-part result."""
    model = make_model(["tx", "ty", "tz", "rx", "ry", "f"])
    lobs, X = two_face_scan(4, n=4096)
    x0 = np.array([{**POSE, "f": F_TRUE}.get(k, 0.0) for k in model.free])
    cell, local, n_cells, _ = panel_cells(X, EDGES, COUNTS)
    design = np.column_stack([np.ones(len(X)), local]) * (cell >= 0)[:, None]
    one, three = (gauss_helmert_mixed(model, lobs, x0, SIGMA, np.zeros((len(lobs), 2)),
                                      np.ones(len(lobs)), cell, design, n_cells,
                                      cell_var0=np.full(3, 1e-8), threads=t, chunk_size=1024)
                  for t in (1, 3))
    assert np.all(np.isfinite(np.asarray(three.v)))
    np.testing.assert_allclose(np.asarray(three.x), np.asarray(one.x), rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(np.asarray(three.cov), np.asarray(one.cov), rtol=1e-9)


def test_compact_inputs_give_the_same_adjustment():
    """A float32 design, bool weights and a float32 start ``v0``, as a large position gives
    them (a float32 design is kept in float32 by the parts), give the float64 inputs'
    adjustment: estimates within 1e-6 of their sigmas, the same rejections."""
    model = make_model(["tx", "ty", "tz", "rx", "ry", "f"])
    lobs, X = two_face_scan(5, n=6000)
    lobs[::499, 0] += 0.01
    x0 = np.array([{**POSE, "f": F_TRUE}.get(k, 0.0) for k in model.free])
    cell, local, n_cells, _ = panel_cells(X, EDGES, COUNTS)
    design = np.column_stack([np.ones(len(X)), local]) * (cell >= 0)[:, None]
    v0 = np.random.default_rng(1).normal(0, 1e-4, lobs.shape) * np.asarray(SIGMA) / SIGMA[0]
    used = np.ones(len(lobs), bool)

    def run(design, weights, v0):
        return gauss_helmert_mixed(model, lobs, x0, SIGMA, np.zeros((len(lobs), 2)), weights,
                                   cell, design, n_cells, cell_var0=np.full(3, 1e-8), v0=v0,
                                   robust_k=4.0, threads=2, chunk_size=1024)

    ref = run(design, used.astype(float), v0)
    got = run(design.astype(np.float32), used, v0.astype(np.float32))
    sd = np.sqrt(np.diag(np.asarray(ref.cov)))
    assert np.max(np.abs(np.asarray(got.x) - np.asarray(ref.x)) / sd) < 1e-6
    np.testing.assert_allclose(np.sqrt(np.diag(np.asarray(got.cov))), sd, rtol=1e-6)
    np.testing.assert_array_equal(np.asarray(got.weights), np.asarray(ref.weights))
    assert int(np.sum(np.asarray(ref.weights) == 0)) > 0


def test_threads_follow_size_and_environment(monkeypatch):
    monkeypatch.setenv("HARTRAO_JAX_THREADS", "4")
    assert mixed_threads(10_000) == 1
    assert mixed_threads(3 << 17) == 3
    assert mixed_threads(1 << 30) == 4
    monkeypatch.setenv("HARTRAO_JAX_THREADS", "1")
    assert mixed_threads(1 << 30) == 1


def test_a_pass_beside_other_work_keeps_its_chunks_to_one_core(monkeypatch):
    """Chunks are capped at PART_CHUNK where a pass is split, or where the process is to use
    fewer cores than the machine's (a Dask worker of one thread); a pass that has the machine
    to itself keeps its chunk."""
    from hartrao_jax import _config
    from hartrao_jax._config import THREADS_ENV
    from hartrao_jax.solver import _kernel
    from hartrao_jax.solver._kernel import PART_CHUNK, part_chunk

    for module in (_config, _kernel):  # a two-core machine
        monkeypatch.setattr(module, "machine_cores", lambda: 2)
    monkeypatch.delenv(THREADS_ENV, raising=False)
    assert part_chunk(8192, 1) == 8192
    assert part_chunk(8192, 2) == PART_CHUNK
    assert part_chunk(1024, 2) == 1024  # a smaller chunk stays
    monkeypatch.setenv(THREADS_ENV, "1")  # a worker of one thread on a two-core machine
    assert part_chunk(8192, 1) == PART_CHUNK
    monkeypatch.setenv(THREADS_ENV, "2")
    assert part_chunk(8192, 1) == 8192
