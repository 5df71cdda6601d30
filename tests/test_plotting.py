"""The mathematics behind the pictures: the envelope of a long signal (running maxima over
windows of samples) and the geometry of the car-pendulum's 3D view (where the cart, the rod
and the bob are drawn), and one smoke test of the figure writers."""

import itertools
import types

import jax
import numpy as np
import pytest

from lgvi_jax import so3
from lgvi_jax.models import CarPendulum
from lgvi_jax.plotting import envelope, window_bounds
from lgvi_jax.studies import car_pendulum as cp

# ------------------------------------------------------------------------------ envelope


@pytest.mark.parametrize("n", [1, 2, 7, 100, 1001, 10**5 + 3])
@pytest.mark.parametrize("windows", [1, 3, 7, 400, 10**6])
def test_windows_cover_every_sample_exactly_once(n, windows):
    bounds = window_bounds(n, windows)
    k = min(n, windows)
    assert len(bounds) == k + 1 and bounds[0] == 0 and bounds[-1] == n
    sizes = np.diff(bounds)
    assert np.all(sizes >= 1) and sizes.max() - sizes.min() <= 1  # as equal as possible
    covered = np.concatenate([np.arange(a, b) for a, b in itertools.pairwise(bounds)])
    np.testing.assert_array_equal(covered, np.arange(n))


@pytest.mark.parametrize("windows", [1, 6, 10, 33])
def test_a_spike_lands_in_exactly_one_window(windows):
    """Through envelope itself: a unit spike at any sample shows in one window only."""
    n = 100
    t = np.linspace(0.0, 1.0, n)
    for j in range(n):
        y = np.zeros(n)
        y[j] = 1.0
        _, top = envelope(t, y, windows)
        assert np.count_nonzero(top) == 1


def test_envelope_of_t_sin_is_its_analytic_maximum():
    """y = t sin(πt/2) sampled at the integers: |y| = t at odd t, 0 at even t, so the
    maximum over a window of samples is its largest odd time."""
    n, windows = 100_001, 37
    t = np.arange(n, dtype=np.float64)
    y = t * np.sin(0.5 * np.pi * t)
    tw, top, low = envelope(t, y, windows, lower=True)
    bounds = window_bounds(n, windows)
    first, last = t[bounds[:-1]], t[bounds[1:] - 1]
    expected = np.where(last % 2 == 1, last, last - 1)
    np.testing.assert_allclose(top, expected, rtol=1e-12)
    np.testing.assert_allclose(low, 0.0, atol=1e-10 * n)  # every window holds an even time
    np.testing.assert_allclose(tw, 0.5 * (first + last), rtol=0, atol=0)
    assert np.all(np.diff(tw) > 0)
    # signed: the maximum of y itself is its largest time ≡ 1 (mod 4), the minimum −(≡ 3)
    _, top_s, low_s = envelope(t, y, windows, absolute=False, lower=True)
    up = last - (last - 1) % 4
    down = last - (last - 3) % 4
    np.testing.assert_allclose(top_s, up, rtol=1e-12)
    np.testing.assert_allclose(low_s, -down, rtol=1e-12)


def test_envelope_of_a_growing_oscillation_follows_its_amplitude():
    """Densely sampled e^(t/10)·sin(ωt) over windows of several periods: each window's
    maximum is the amplitude near its end, e^(t_end/10), to the sampling's resolution."""
    t = np.linspace(0.0, 40.0, 400_001)
    omega = 2 * np.pi * 3.0
    _, top = envelope(t, np.exp(t / 10) * np.sin(omega * t), 20)
    bounds = window_bounds(len(t), 20)
    t_end = t[bounds[1:] - 1]
    # the last peak sits within one period of the window's end
    assert np.all(top <= np.exp(t_end / 10) * (1 + 1e-12))
    assert np.all(top >= np.exp((t_end - 2 * np.pi / omega) / 10))


@pytest.mark.parametrize("c", [3.5, -2.0, 0.0])
def test_envelope_of_a_constant_is_the_constant(c):
    t = np.linspace(0.0, 5.0, 1000)
    tw, top, low = envelope(t, np.full_like(t, c), 40, lower=True)
    assert len(tw) == 40
    np.testing.assert_array_equal(top, abs(c))
    np.testing.assert_array_equal(low, abs(c))
    _, top_s, low_s = envelope(t, np.full_like(t, c), 40, absolute=False, lower=True)
    np.testing.assert_array_equal(top_s, c)
    np.testing.assert_array_equal(low_s, c)


def test_more_windows_than_samples_gives_the_signal():
    t = np.linspace(0.0, 1.0, 11)
    y = np.cos(7 * t) - 0.5
    tw, top = envelope(t, y, 400)
    np.testing.assert_array_equal(tw, t)
    np.testing.assert_array_equal(top, np.abs(y))


def test_min_span_makes_windows_longer_than_it():
    t = np.linspace(0.0, 100.0, 10_001)
    y = np.sin(t)
    tw, _ = envelope(t, y, 400, min_span=2 * np.pi * 4)
    assert len(tw) == int(100.0 // (2 * np.pi * 4)) == 3
    assert len(envelope(t, y, 400, min_span=0.01)[0]) == 400  # already longer
    assert len(envelope(t, y, 400, min_span=1e3)[0]) == 1  # one window at least


def test_a_nan_is_not_hidden():
    t = np.linspace(0.0, 1.0, 100)
    y = np.ones(100)
    y[57] = np.nan
    _, top = envelope(t, y, 10)
    assert np.isnan(top).sum() == 1 and np.isnan(top[5])


def test_envelope_rejects_mismatched_shapes():
    with pytest.raises(ValueError, match="same length"):
        envelope(np.arange(5.0), np.arange(4.0))
    with pytest.raises(ValueError, match="windows >= 1"):
        window_bounds(5, 0)


# ------------------------------------------------------------- car-pendulum geometry


def _rot_z(angle):
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def test_geometry_identity_attitude():
    model = CarPendulum()
    rho = np.asarray(model.rho_c)
    q = np.array([0.3, -1.2])
    g = cp.motion_geometry(model, np.eye(3), q)
    np.testing.assert_array_equal(g["pivot"], [0.3, -1.2, 0.0])
    np.testing.assert_allclose(g["bob"], [0.3 + rho[0], -1.2 + rho[1], rho[2]], rtol=0,
                               atol=1e-15)
    # the cart: a rectangle in the plane z = 0 centred on the pivot, axis-aligned
    cart = g["cart"]
    assert cart.shape == (4, 3)
    np.testing.assert_array_equal(cart[:, 2], 0.0)
    np.testing.assert_allclose(cart.mean(axis=0), g["pivot"], atol=1e-15)
    size = np.linalg.norm(rho)
    np.testing.assert_allclose(np.ptp(cart[:, :2], axis=0), size * np.asarray(cp.CART_SIZE))
    # body axes at the bob: bob + s e_i
    s = cp.BODY_AXIS_LENGTH * size
    np.testing.assert_allclose(g["body_axes"], g["bob"] + s * np.eye(3), atol=1e-15)


def test_geometry_known_rotations():
    """Hand-computed: ρ_c = (0.25, 0.25, 1); a quarter turn about the vertical gives
    R ρ_c = (−0.25, 0.25, 1); the paper's R0 (rows (1,0,0), (0,0,−1), (0,1,0)) gives
    (0.25, −1, 0.25)."""
    model = CarPendulum()
    q = np.array([-0.125, -0.0125])
    g = cp.motion_geometry(model, _rot_z(np.pi / 2), q)
    np.testing.assert_allclose(g["bob"] - g["pivot"], [-0.25, 0.25, 1.0], atol=1e-15)
    R0 = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    g = cp.motion_geometry(model, R0, q)
    np.testing.assert_allclose(g["bob"], [0.125, -1.0125, 0.25], atol=1e-15)
    s = cp.BODY_AXIS_LENGTH * np.linalg.norm(model.rho_c)
    np.testing.assert_allclose((g["body_axes"] - g["bob"]) / s, R0.T, atol=1e-15)
    # another ρ_c: straight down from the hinge (e3 points down) at R = I
    g = cp.motion_geometry(CarPendulum(rho_c=(0.0, 0.0, 0.5)), np.eye(3), q)
    np.testing.assert_allclose(g["bob"], [-0.125, -0.0125, 0.5], atol=1e-15)


def test_geometry_batched_matches_the_model():
    """Random attitudes: bob = cart + R ρ_c, as the model's pendulum_centre; the rod keeps
    its length |ρ_c|; the body axes are R's columns."""
    model = CarPendulum()
    rng = np.random.default_rng(3)
    R = np.asarray(jax.vmap(so3.exp)(rng.normal(size=(50, 3)) * 2.0))
    q = rng.normal(size=(50, 2))
    g = cp.motion_geometry(model, R, q)
    rho = np.asarray(model.rho_c)
    pivot = np.concatenate([q, np.zeros((50, 1))], axis=1)
    np.testing.assert_allclose(g["bob"], pivot + R @ rho, atol=1e-14)
    states = jax.vmap(lambda Ri, qi: model.state_from_velocities(
        Ri, np.zeros(3), qi, np.zeros(2)))(R, q)
    np.testing.assert_allclose(g["bob"], np.asarray(jax.vmap(model.pendulum_centre)(states)),
                               atol=1e-14)
    np.testing.assert_allclose(np.linalg.norm(g["bob"] - g["pivot"], axis=-1),
                               np.linalg.norm(rho), rtol=1e-14)
    s = cp.BODY_AXIS_LENGTH * np.linalg.norm(rho)
    np.testing.assert_allclose((g["body_axes"] - g["bob"][:, None, :]) / s,
                               np.swapaxes(R, 1, 2), atol=1e-14)
    assert g["cart"].shape == (50, 4, 3)


def test_frames_are_equally_spaced_saved_states():
    traj = types.SimpleNamespace(t=np.arange(0, 401) * 0.05)
    idx = cp.motion_frames(traj, 2.0, 9)
    np.testing.assert_array_equal(idx, np.arange(0, 41, 5))
    assert cp.motion_frames(traj, 100.0, 3)[-1] == 400  # clipped to the run's end


# ------------------------------------------------------------------------- writers


def _swinging_trajectory(n=41, dt=0.05):
    """A made-up motion (no simulation): a spinning, swinging pendulum on a moving cart."""
    t = np.arange(n) * dt
    R = np.asarray(jax.vmap(so3.exp)(np.stack([0.8 * np.sin(3 * t), 0.3 * np.cos(2 * t),
                                               5.0 * t], axis=1)))
    q = np.stack([0.3 * t, -0.1 * t], axis=1)
    return types.SimpleNamespace(t=t, state=types.SimpleNamespace(R=R, q=q))


def test_motion_figures_write_png_and_gif(tmp_path):
    model, traj = CarPendulum(), _swinging_trajectory()
    cfg = {**cp.config(quick=True), "motion_snapshots_t": 1.0, "motion_gif_t": 1.0}
    names = cp.motion_figures(model, traj, cfg, tmp_path)
    assert names[0] == "motion_snapshots.png"
    png = (tmp_path / "motion_snapshots.png").read_bytes()
    assert len(png) > 10_000 and png[:8] == b"\x89PNG\r\n\x1a\n"
    if "motion.gif" in names:
        gif = (tmp_path / "motion.gif").read_bytes()
        assert gif[:6] == b"GIF89a"
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temp left
    anim = cp.motion_animation(model, traj, t_final=1.0, frames=4)
    assert "<img" in anim.to_jshtml()
