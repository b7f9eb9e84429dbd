"""Kalman filter (SPEC §3.1, paper eq. 1) against filterpy.

filterpy's ``KalmanFilter`` is given the same F, B, Q per interval and the
same H, R; its ``update`` is the Joseph form ``P = (I-KH)P(I-KH)' + KRK'``
(filterpy 1.4.5, kalman_filter.py). The event loop (time order, accelerometer
first at equal times, held input, start at the first position sample) is
written here from the SPEC text.
"""

from __future__ import annotations

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter as FilterpyKF
from hypothesis import given, settings
from hypothesis import strategies as st

import shocktwin

SIGMAS = {"sigma_accel": 0.3, "sigma_bias": 0.01, "sigma_position": 1e-3}
# Named tolerance (the brief: 1e-9 relative): relative to each channel's
# largest magnitude, so that near-zero crossings do not divide by ~0.
RTOL = 1e-9


def filterpy_reference(
    t_acc_ns, a_rel, t_pos_ns, pos, sigma_accel, sigma_bias, sigma_position, *, after_all=True
):
    """State at each accelerometer time, after every event at that time; NaN before the start.

    ``after_all=False`` records the state right after the accelerometer event
    instead (a plausible mistake, used to show the comparison can fail).
    """
    events = sorted(
        [(int(t), 0, i) for i, t in enumerate(t_acc_ns)] + [(int(t), 1, i) for i, t in enumerate(t_pos_ns)],
        key=lambda e: (e[0], e[1]),
    )
    kf = FilterpyKF(dim_x=3, dim_z=1, dim_u=1)
    kf.H = np.array([[1.0, 0.0, 0.0]])
    kf.R = np.array([[sigma_position**2]])
    started, u, t_prev = False, 0.0, 0
    out = np.full((len(t_acc_ns), 3), np.nan)
    k = 0
    while k < len(events):
        t = events[k][0]
        group = []
        while k < len(events) and events[k][0] == t:
            group.append(events[k])
            k += 1
        for _, kind, i in group:
            if started:
                dt = (t - t_prev) * 1e-9
                g = np.array([[dt**2 / 2], [dt], [0.0]])
                f = np.array([[1.0, dt, -(dt**2) / 2], [0.0, 1.0, -dt], [0.0, 0.0, 1.0]])
                q = sigma_accel**2 * (g @ g.T) + np.diag([0.0, 0.0, sigma_bias**2 * dt])
                kf.predict(u=u, B=g, F=f, Q=q)
                t_prev = t
            if kind == 0:
                u = float(a_rel[i])
                if started and not after_all:
                    out[i] = kf.x[:, 0]
            elif not started:
                kf.x = np.array([[pos[i]], [0.0], [0.0]])
                kf.P = np.diag([sigma_position**2, 1.0, 1.0])
                started, t_prev = True, t
            else:
                kf.update(np.array([[pos[i]]]))
        if started and after_all:
            for _, kind, i in group:
                if kind == 0:
                    out[i] = kf.x[:, 0]
    return out


def dyno_streams(seed=0, duration_s=3.0, t0_ns=5_000_000_000):
    """1 kHz accelerometer and 100 Hz potentiometer, both with clock jitter,
    a bias, 20 accelerometer samples before the first position sample and a
    share of position samples at exactly an accelerometer time."""
    rng = np.random.default_rng(seed)
    n_acc = int(duration_s * 1000)
    t_acc = t0_ns + np.arange(n_acc) * 1_000_000 + rng.integers(-200_000, 200_000, n_acc)
    t_acc.sort()
    t_pos = t0_ns + 20_000_000 + np.arange(int(duration_s * 100) - 3) * 10_000_000
    t_pos = t_pos + rng.integers(-2_000_000, 2_000_000, t_pos.size)
    same = rng.random(t_pos.size) < 0.3  # equal-time events
    t_pos[same] = t_acc[np.searchsorted(t_acc, t_pos[same]).clip(max=n_acc - 1)]
    t_pos.sort()
    w, amp = 2 * np.pi * 2.0, 0.04
    s_acc, s_pos = (t_acc - t0_ns) * 1e-9, (t_pos - t0_ns) * 1e-9
    a_rel = -amp * w**2 * np.sin(w * s_acc) + 0.3 + rng.normal(0, 0.1, n_acc)
    pos = amp * np.sin(w * s_pos) + rng.normal(0, 1e-3, t_pos.size)
    return t_acc, a_rel, t_pos, pos


def assert_close_to_reference(got, ref):
    for j, name in enumerate(["position_m", "velocity_mps", "bias_mps2"]):
        want = ref[:, j]
        started = ~np.isnan(want)
        assert np.array_equal(np.isnan(got[name]), ~started), f"{name}: NaN rows differ"
        scale = np.max(np.abs(want[started]))
        np.testing.assert_allclose(got[name][started], want[started], rtol=RTOL, atol=RTOL * scale, err_msg=name)


def test_kalman_matches_filterpy():
    t_acc, a_rel, t_pos, pos = dyno_streams()
    assert np.intersect1d(t_acc, t_pos).size > 50  # equal-time events are exercised
    to_s = lambda t_ns: t_ns * 1e-9  # noqa: E731
    got = shocktwin.KalmanFilter(**SIGMAS).run(to_s(t_acc), a_rel, to_s(t_pos), pos)
    ref = filterpy_reference(t_acc, a_rel, t_pos, pos, **SIGMAS)
    assert set(got) == {"t_s", "position_m", "velocity_mps", "bias_mps2"}
    np.testing.assert_array_equal(got["t_s"], to_s(t_acc))
    assert np.isnan(got["velocity_mps"][:10]).all()  # before the first position sample
    assert_close_to_reference(got, ref)
    # it tracked the motion and found the bias: the comparison is not of zeros
    assert np.nanmax(np.abs(got["velocity_mps"])) > 0.4
    assert abs(got["bias_mps2"][-1] - 0.3) < 0.1


def test_reference_sees_the_equal_time_update():
    """Rows at equal-time events include the position update (so the test above can fail).

    (Which of two equal-time events is taken first cannot change the state
    after both: the second propagates over dt = 0, the identity.)
    """
    t_acc, a_rel, t_pos, pos = dyno_streams()
    ref = filterpy_reference(t_acc, a_rel, t_pos, pos, **SIGMAS)
    other = filterpy_reference(t_acc, a_rel, t_pos, pos, **SIGMAS, after_all=False)
    ok = ~np.isnan(ref[:, 1])
    assert np.max(np.abs(other[ok, 1] - ref[ok, 1])) > 1e3 * RTOL * np.max(np.abs(ref[ok, 1]))


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    sigma_accel=st.floats(0.01, 5.0),
    sigma_bias=st.floats(1e-4, 0.5),
    sigma_position=st.floats(1e-4, 1e-2),
)
def test_kalman_matches_filterpy_hypothesis(seed, sigma_accel, sigma_bias, sigma_position):
    rng = np.random.default_rng(seed)
    t_acc = np.sort(rng.integers(0, 200_000_000, rng.integers(1, 120)))
    t_pos = np.sort(np.concatenate([rng.integers(0, 200_000_000, rng.integers(1, 15)), rng.choice(t_acc, 3)]))
    a_rel = rng.normal(0, 5, t_acc.size)
    pos = rng.normal(0, 0.03, t_pos.size)
    sigmas = {"sigma_accel": sigma_accel, "sigma_bias": sigma_bias, "sigma_position": sigma_position}
    got = shocktwin.KalmanFilter(**sigmas).run(t_acc * 1e-9, a_rel, t_pos * 1e-9, pos)
    ref = filterpy_reference(t_acc, a_rel, t_pos, pos, **sigmas)
    if np.isnan(ref[:, 0]).all():
        assert np.isnan(got["position_m"]).all()
    else:
        assert_close_to_reference(got, ref)


def test_bad_inputs_are_named():
    kf = shocktwin.KalmanFilter(**SIGMAS)
    with pytest.raises(shocktwin.InputError, match="t_pos"):
        kf.run([0.0, 0.001], [0.0, 0.0], [0.01, 0.0], [0.0, 0.0])  # not sorted
    with pytest.raises(shocktwin.InputError, match=r"t_acc`\[1\]"):
        kf.run([0.0, np.nan], [0.0, 0.0], [0.0], [0.0])  # a time must be finite
    with pytest.raises(shocktwin.InputError, match="a_rel"):
        kf.run([0.0, 0.001], [0.0], [0.0], [0.0])
    assert isinstance(shocktwin.InputError("x"), ValueError)
    # an input of the wrong shape names the argument and says what it got
    with pytest.raises(TypeError, match=r"argument 't_pos': expected a 1-D .* 0-D value.*list of one"):
        kf.run([0.0], [0.0], 0.0, [0.0])
    with pytest.raises(TypeError, match=r"argument 'a_rel': expected a 1-D .* shape \(1, 2\)"):
        kf.run([0.0, 0.001], [[0.0, 0.0]], [0.0], [0.0])


def test_bad_sigma_names_the_parameter():
    with pytest.raises(shocktwin.ParamsError, match="sigma_bias"):
        shocktwin.KalmanFilter(sigma_accel=0.2, sigma_bias=-1.0, sigma_position=1e-3)
