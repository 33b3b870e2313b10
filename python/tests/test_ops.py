"""The ops as a user meets them: bad input named, panics contained, the GIL released, inputs left
alone, and the backward passes agreeing with central finite differences of the forward ones."""

import threading
import time

import numpy as np
import pytest

import xscale

from conftest import GOLDEN

TINY = dict(levels=4, features=2, log2_table_size=12, base_resolution=4, per_level_scale=2.0)


def rng(seed=0):
    return np.random.default_rng(seed)


# ---------------------------------------------------------------------------------------------
# Bad input: TypeError / ValueError with the argument named, never a crash


def test_bad_input_is_named():
    g = xscale.HashGrid(**TINY)
    t = g.init_table(0)
    x = rng().random((5, 3))
    with pytest.raises(TypeError, match=r"positions: dtype float32, expected float64"):
        g.forward(t, x.astype(np.float32))
    with pytest.raises(TypeError, match=r"positions: expected a numpy.ndarray, got list"):
        g.forward(t, x.tolist())
    with pytest.raises(ValueError, match=r"positions: not C-contiguous"):
        g.forward(t, np.asfortranarray(x))
    with pytest.raises(ValueError, match=r"positions: shape \[5, 4\], expected \(M, 3\): axis 1 is 4"):
        g.forward(t, rng().random((5, 4)))
    with pytest.raises(ValueError, match=r"table: shape .*axis 0 is 10, expected 8768"):
        g.forward(np.zeros((10, 2), np.float32), x)
    bad = x.copy()
    bad[3, 1] = np.nan
    with pytest.raises(ValueError, match=r"positions: row 3 component 1 is NaN"):
        g.forward(t, bad)
    with pytest.raises(TypeError, match=r"table: dtype int32, expected float32 or float64"):
        g.forward(t.astype(np.int32), x)
    with pytest.raises(ValueError, match=r"d_out: .*axis 0 \(M\) is 4, but M = 5 \(from positions\)"):
        g.backward_table(x, np.zeros((4, 8), np.float32))
    with pytest.raises(ValueError, match=r"mode \"cuda\": expected \"f64\" or \"tcnn\""):
        g.forward(t, x, mode="cuda")
    with pytest.raises(ValueError, match=r"grid config: unknown field `levls`"):
        xscale.HashGrid(levls=4, features=2, log2_table_size=12, base_resolution=4, per_level_scale=2.0)
    with pytest.raises(ValueError, match=r"features = 3 must be one of 1, 2, 4, 8"):
        xscale.HashGrid(**{**TINY, "features": 3})
    with pytest.raises(ValueError, match=r"scale of level 1 is -1"):
        xscale.HashGrid(**TINY, scales=np.array([3, -1, 7, 15], np.float32))
    # The other ops.
    with pytest.raises(ValueError, match=r"valid: pixel 1 has no valid sub-sample"):
        xscale.pool_forward(np.zeros((2, 2, 3)), np.array([[1, 0], [0, 0]], np.uint8))
    with pytest.raises(ValueError, match=r"valid: pixel 0 sub-sample 1 is 2, expected 0 or 1"):
        xscale.pool_backward(np.zeros((2, 3)), np.array([[1, 2], [1, 0]], np.uint8))
    with pytest.raises(ValueError, match=r"view: pixel 2: view 3 has no appearance code \(the table has 3 rows"):
        xscale.appearance_forward(np.zeros((3, 2)), np.array([0, -1, 3], np.int32))
    with pytest.raises(ValueError, match=r"weights\[1\]: shape \[3, 5\], expected \(out, 4\)"):
        xscale.mlp_forward(np.zeros((2, 6)), [np.zeros((4, 6)), np.zeros((3, 5))])
    with pytest.raises(ValueError, match=r"kind \"l3\""):
        xscale.loss_forward(np.zeros((2, 3)), np.zeros((2, 3), np.float32), kind="l3")
    with pytest.raises(ValueError, match=r"chunks: expected row boundaries \[0, …, 4\]"):
        xscale.linear_backward(np.zeros((4, 2)), np.zeros((3, 2)), np.zeros((4, 3)), chunks=[0, 5])
    with pytest.raises(TypeError, match=r"float64 directions with dtype float32"):
        xscale.sh_forward(np.zeros((2, 3)), dtype="float32")


def test_bad_files_and_models_are_named(tmp_path):
    p = tmp_path / "not.safetensors"
    p.write_bytes(b"hello world, not a safetensors file")
    with pytest.raises(ValueError, match=str(p)):
        xscale.load(p)
    ck = xscale.load(GOLDEN / "tiny-f64-linear" / "checkpoint.safetensors")
    b = xscale.load(GOLDEN / "tiny-f64-linear" / "batch.safetensors")
    broken = xscale.Tensors({k: v for k, v in ck.items() if k != "shader.layers.1.weight"}, ck.metadata)
    with pytest.raises(ValueError, match=r"shader.layers.1.weight"):
        xscale.Model(broken)
    with pytest.raises(ValueError, match=r"not a checkpoint: this file is a batch"):
        xscale.Model(b)
    m = xscale.Model(ck)
    bad = xscale.Tensors(dict(b))
    bad["batch.view"] = bad["batch.view"].copy()
    bad["batch.view"][5] = 99
    with pytest.raises(ValueError, match=r"pixel 5: view 99 has no appearance code"):
        m.step(bad)
    with pytest.raises(ValueError, match=r"kink_threshold: the kink analysis is part of the f64"):
        m.step(b, "f32", kink_threshold=1e-5)
    with pytest.raises(TypeError, match=r"dtype float16"):
        xscale.save(tmp_path / "h.safetensors", {"x": np.zeros(3, np.float16)})


def test_a_rust_panic_is_a_runtime_error_and_the_interpreter_goes_on():
    for worker in (False, True):
        with pytest.raises(RuntimeError, match=r"xscale internal error .*deliberate panic"):
            xscale._xscale._panic_for_test(worker)
    g = xscale.HashGrid(**TINY)
    assert g.forward(g.init_table(0), rng().random((3, 3))).shape == (3, 8)


# ---------------------------------------------------------------------------------------------
# Threads, the GIL, inputs


def test_inputs_are_not_modified_and_results_are_new_arrays():
    g = xscale.HashGrid(**TINY, interpolation="smoothstep")
    t = g.init_table(1).astype(np.float64)
    x = rng(1).random((300, 3))
    d = rng(2).standard_normal((300, 8))
    copies = [a.copy() for a in (t, x, d)]
    outs = [g.forward(t, x), g.backward_table(x, d), g.backward_positions(t, x, d)]
    for a, c in zip((t, x, d), copies):
        assert np.array_equal(a, c)
    for o in outs:
        assert o.flags.owndata or o.base is not None and not np.shares_memory(o, t)
        assert not any(np.shares_memory(o, a) for a in (t, x, d))
    y = rng(3).standard_normal((10, 4))
    r = xscale.relu_forward(y)
    assert not np.shares_memory(r, y) and (y < 0).any() and np.array_equal(r, np.maximum(y, 0))


def test_the_gil_is_released_while_rust_computes():
    """A Python thread keeps running while a long Rust call is in progress."""
    g = xscale.HashGrid(levels=16, features=2, log2_table_size=19, base_resolution=16, per_level_scale=1.38)
    t = g.init_table(0)
    x = rng().random((400_000, 3))
    ticks = []
    stop = threading.Event()

    def count():
        while not stop.is_set():
            ticks.append(time.perf_counter())

    th = threading.Thread(target=count)
    th.start()
    time.sleep(0.01)
    t0 = time.perf_counter()
    g.forward(t, x)
    t1 = time.perf_counter()
    stop.set()
    th.join()
    during = [s for s in ticks if t0 < s < t1]
    assert t1 - t0 > 0.02, "the call was too short to tell"
    # With the GIL held the counter would be frozen for the whole call.
    assert len(during) > 100, (len(during), t1 - t0)


def test_thread_count_is_settable():
    before = xscale.get_num_threads()
    try:
        xscale.set_num_threads(1)
        assert xscale.get_num_threads() == 1
        xscale.set_num_threads(3)
        assert xscale.get_num_threads() == 3
    finally:
        xscale.set_num_threads(before)


# ---------------------------------------------------------------------------------------------
# Backward passes against central finite differences of the forward passes (f64)


def fd(f, x, h=1e-6):
    g = np.zeros_like(x)
    for i in np.ndindex(x.shape):
        xp, xm = x.copy(), x.copy()
        xp[i] += h
        xm[i] -= h
        g[i] = (f(xp) - f(xm)) / (2 * h)
    return g


@pytest.mark.parametrize("interp", ["linear", "smoothstep"])
def test_grid_backward_matches_finite_differences(interp):
    g = xscale.HashGrid(**{**TINY, "interpolation": interp})
    t = rng(4).uniform(-1, 1, (g.n_entries, 2))
    x = rng(5).uniform(0.05, 0.95, (6, 3))
    d = rng(6).standard_normal((6, g.out_dim))
    # Keep the points away from cell borders (the forward is not differentiable there).
    for s in g.scales:
        p = s * x + 0.5
        assert (np.abs(p - np.round(p)) > 1e-4).all()
    loss = lambda xx: float((g.forward(t, xx) * d).sum())
    assert np.allclose(g.backward_positions(t, x, d), fd(loss, x), rtol=1e-6, atol=1e-8)
    lt = lambda tt: float((g.forward(tt, x) * d).sum())
    sub = np.unique(g.corners(x, 2)[0].ravel())[:6]  # entries touched on level 2
    num = np.array([[(lt(_bump(t, e, f, 1e-6)) - lt(_bump(t, e, f, -1e-6))) / 2e-6 for f in range(2)] for e in sub])
    assert np.allclose(g.backward_table(x, d)[sub], num, rtol=1e-6, atol=1e-9)


def _bump(t, e, f, h):
    t = t.copy()
    t[e, f] += h
    return t


def test_sh_mlp_loss_backward_match_finite_differences():
    r = rng(7)
    dirs = r.standard_normal((5, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    w = r.standard_normal((5, 16))
    assert np.allclose(xscale.sh_backward(dirs, w), fd(lambda d: float((xscale.sh_forward(d, dtype="float64") * w).sum()), dirs),
                       rtol=1e-6, atol=1e-8)
    x = r.standard_normal((4, 6))
    ws = [r.standard_normal((5, 6)), r.standard_normal((3, 5))]
    bs = [r.standard_normal(5), r.standard_normal(3)]
    g = r.standard_normal((4, 3))
    hidden, y = xscale.mlp_forward(x, ws, bs)
    d_x, d_ws, d_bs = xscale.mlp_backward(x, ws, hidden, g, biases=bs)
    f = lambda xx: float((xscale.mlp_forward(xx, ws, bs)[1] * g).sum())
    assert np.allclose(d_x, fd(f, x), rtol=1e-6, atol=1e-8)
    f = lambda w0: float((xscale.mlp_forward(x, [w0, ws[1]], bs)[1] * g).sum())
    assert np.allclose(d_ws[0], fd(f, ws[0]), rtol=1e-6, atol=1e-8)
    f = lambda b1: float((xscale.mlp_forward(x, ws, [bs[0], b1])[1] * g).sum())
    assert np.allclose(d_bs[1], fd(f, bs[1]), rtol=1e-6, atol=1e-8)
    tgt = r.random((4, 3)).astype(np.float32)
    rgb = r.random((4, 3))
    for kind in ("l1", "l2", "smooth_l1"):
        f = lambda z: xscale.loss_forward(xscale.sigmoid_forward(z), tgt, kind=kind, delta=0.1)
        z = np.log(rgb / (1 - rgb))
        s = xscale.sigmoid_forward(z)
        d = xscale.sigmoid_backward(s, xscale.loss_backward(s, tgt, kind=kind, delta=0.1))
        assert np.allclose(d, fd(f, z), rtol=1e-5, atol=1e-9), kind


def test_pooling_codes_and_level_weights_are_what_the_spec_says():
    r = rng(8)
    feat = r.standard_normal((4, 3, 2))
    valid = np.array([[1, 0, 1], [0, 1, 0], [1, 1, 1], [0, 0, 1]], np.uint8)
    pooled = xscale.pool_forward(feat, valid)
    for i in range(4):
        assert np.allclose(pooled[i], feat[i][valid[i] == 1].mean(axis=0), rtol=1e-15)
    d = xscale.pool_backward(np.ones((4, 2)), valid)
    assert np.allclose(d[..., 0], valid / valid.sum(1, keepdims=True))
    codes = r.standard_normal((3, 2))
    got = xscale.appearance_forward(codes, np.array([2, -1], np.int32))
    assert np.array_equal(got[0], codes[2]) and np.allclose(got[1], codes.mean(0))
    dc = xscale.appearance_backward(np.array([[1.0, 2.0], [3.0, 6.0]]), np.array([2, -1], np.int32), 3)
    assert np.allclose(dc, np.array([[1, 2], [1, 2], [2, 4]]))
    scales = np.array([3, 7, 15, 31], np.float32)
    fp = np.array([0.1, 1 / 7, 0.5, 0.01], np.float32)
    w, act = xscale.level_weights(scales, fp)

    def spec_w(r):  # SPEC §4.10
        if r <= 1:
            return 1.0
        if r >= 4:
            return 0.0
        t = np.log2(r) / 2
        return 1 - t * t * (3 - 2 * t)

    want = np.array([[spec_w(float(f) * float(s)) for s in scales] for f in fp])
    assert np.allclose(w, want, rtol=0, atol=1e-15)
    assert act.tolist() == [int((row > 0).nonzero()[0].max()) + 1 for row in want]
    assert 0 < want[0, 3] < 1 and want[2, 3] == 0 and (want[3] == 1).all()
    x = np.ones((4, 8))
    assert np.array_equal(xscale.apply_level_weights(w, x)[:, ::2], w)
