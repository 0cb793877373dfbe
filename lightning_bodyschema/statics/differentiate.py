"""Joint velocities and accelerations of a sampled motion: a Savitzky-Golay differentiator (a polynomial of degree
``polyorder`` fitted by least squares over a window of frames around each frame, differentiated; the first and last
half-windows from the fit of the first and last whole window).

What it costs in accuracy, measured on a known analytic motion (``tools/bench_static_opt.py --motion`` prints it):
``q = 0.5 sin(2 pi t)`` [rad] over 2 s sampled every 2 ms, the default 0.05 s window (25 frames) and degree 3, misses
the velocity by up to 1.2e-4 rad/s and the acceleration by up to 0.035 rad/s^2 (0.18 % of its 19.7 rad/s^2 peak);
with 1e-5 rad of white noise on the positions the acceleration misses by up to 0.085 rad/s^2 (a second difference
misses by 20.9 rad/s^2). A wider window or a lower degree smooths more and bends fast motions more. Give
``qvel_<joint>``/``qacc_<joint>`` columns to use a motion's own derivatives instead. numpy and scipy.
"""
from __future__ import annotations

import numpy as np

from ..errors import BodySchemaInputError

WINDOW_S, POLYORDER = 0.05, 3
UNIFORM_RTOL = 1e-6  # frames this close to evenly spaced count as evenly spaced (times written with 7 digits)


def frame_step_s(t) -> float:
    """The frames' common spacing [s]; refused when the frames are not evenly spaced."""
    steps = np.diff(np.asarray(t, float))
    if not len(steps) or (steps <= 0).any():
        raise BodySchemaInputError("the motion's t must hold at least two frames, strictly increasing")
    step = float(np.median(steps))
    if np.abs(steps - step).max() > UNIFORM_RTOL * step:
        raise BodySchemaInputError(f"frames are not evenly spaced (steps {steps.min():.6g} to {steps.max():.6g} s): "
                                   "the differentiator needs evenly spaced frames; resample the motion or give "
                                   "qvel_<joint> and qacc_<joint> columns")
    return step


def differentiate(t, q, window_s: float = WINDOW_S, polyorder: int = POLYORDER) -> tuple[np.ndarray, np.ndarray]:
    """``(qvel, qacc)`` (B, N) of positions ``q`` (B, N) at evenly spaced times ``t`` (B,) [s] (module docstring):
    the window is ``window_s`` rounded to an odd number of frames, at least ``polyorder + 2``."""
    from scipy.signal import savgol_filter

    if not np.isfinite(window_s) or window_s <= 0:
        raise BodySchemaInputError(f"the differentiator's window is {window_s} s; give a positive number of seconds")
    step = frame_step_s(t)
    frames = max(polyorder + 2, int(round(window_s / step)))
    frames += 1 - frames % 2  # odd: centred on its frame
    if frames > len(q):
        raise BodySchemaInputError(f"the motion has {len(q)} frames; the differentiator's window needs {frames} "
                                   f"({window_s} s at {step:.6g} s per frame, degree {polyorder})")
    return tuple(savgol_filter(q, frames, polyorder, deriv=k, delta=step, axis=0) for k in (1, 2))
