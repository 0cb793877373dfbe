"""``tools/static_opt.py --motion``: inverse dynamics with faults over a motion file (``statics.dynamics``), written per
frame; ``--track`` simulates it in MuJoCo (``statics.track``); ``--plot`` draws the activations over time.

Output: ``.csv`` (``t``, the posture, ``status``, ``status_code``, ``control_clipped`` (how many muscles' excitations
were clipped to [0, 1]), then ``<muscle>.activation``, ``<muscle>.control``, ``<muscle>.tension_n`` per muscle, then
``<joint>.residual_nm`` per residual actuator, then on a floating root ``<root>_tx.residual_n`` .. ``_tz`` [N] and
``<root>_rx.residual_nm`` .. ``_rz`` [N m], its residual actuators: ``statics.root``) or ``.npz`` (arrays ``t``,
``q``, ``qvel``, ``qacc``, ``tau_nm``, ``activation``, ``control``, ``control_clipped``, ``tension_n``,
``l_motor_m``, ``residual_nm``, ``residual_dofs``, ``status``, ``status_code``, ``joints``, ``muscles``,
``objective``; on a floating root ``root_qpos``, ``root_qvel``, ``root_qacc``, ``root_residual``, ``root_dofs``),
written to a temporary name and renamed.
"""
from __future__ import annotations

import csv
import io

import numpy as np

from ..status import status_codes, status_names
from .common import write_bytes, write_npz

CHUNK = 256  # frames per solve: the progress bar's step


def solve_file(body, args, faults):
    """The ``MotionResult`` of ``args.motion`` (velocities and accelerations differentiated where not given)."""
    from ..statics.differentiate import differentiate
    from ..statics.root import free_roots, root_derivatives
    from .motion_files import read_motion

    roots = [joint for joint, _ in free_roots(body.source)] if body.fixed_base else []
    t, q, qvel, qacc, root = read_motion(args.motion, body.model, roots, body.source)
    body.model.check_q(q, within_range=True)
    if qvel is None or qacc is None:
        derived = differentiate(t, q, args.smooth_window)
        qvel, qacc = (given if given is not None else d for given, d in zip((qvel, qacc), derived))
    if root is not None and (root[1] is None or root[2] is None):
        derived = root_derivatives(t, root[0], lambda t, x: differentiate(t, x, args.smooth_window))
        root = (root[0], *(given if given is not None else d for given, d in zip(root[1:], derived)))
    return _solve(body, t, q, qvel, qacc, faults, args, root)


def _solve(body, t, q, qvel, qacc, faults, args, root=None):
    from tqdm.auto import tqdm

    from ..statics.dynamics import frame_controls, solve_motion
    from .posture_files import concatenate

    parts = []
    with tqdm(total=len(q), desc="frames", unit="frame", disable=args.no_progress or len(q) <= CHUNK) as bar:
        for k in range(0, len(q), CHUNK):
            rows = slice(k, k + CHUNK)
            parts.append(solve_motion(body, q[rows], qvel[rows], qacc[rows], faults, None, args.residual,
                                      args.residual_weight, args.objective, solver=args.solver, t=t[rows],
                                      device=args.device, root=None if root is None else [r[rows] for r in root]))
            bar.update(len(parts[-1].q))
    result = concatenate(parts)
    if result.activation is not None:  # across the chunks' seams: each frame's control reaches the next frame
        result.control, result.control_clipped = frame_controls(body, result.activation, result.t)
    return result


def _csv_text(result) -> str:
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    fields = [("activation", result.activation), ("control", result.control), ("tension_n", result.tension_n)]
    fields = [(label, values) for label, values in fields if values is not None]
    writer.writerow(["t"] + list(result.joints) + ["status", "status_code", "control_clipped"]
                    + [f"{m}.{label}" for m in result.muscles for label, _ in fields]
                    + [f"{j}.residual_nm" for j in result.residual_dofs]
                    + [f"{j}.residual_{'n' if j[-2] == 't' else 'nm'}" for j in result.root_dofs])
    per_muscle = np.stack([values for _, values in fields], axis=2).reshape(len(result.q), -1)
    residual = np.hstack([x for x in (result.residual_nm, result.root_residual) if x is not None]
                         + [np.zeros((len(result.q), 0))])
    clipped = np.zeros(len(result.q), int) if result.control_clipped is None else result.control_clipped.sum(1)
    for row in zip(result.t, result.q, status_names(result.status), status_codes(result.status), clipped,
                   per_muscle, residual):
        t, q, name, code, n_clipped, values, r = row
        writer.writerow([repr(float(t))] + [repr(float(v)) for v in q] + [name, int(code), int(n_clipped)]
                        + [repr(float(v)) for v in values] + [repr(float(v)) for v in r])
    return buffer.getvalue()


def write_motion(path: str, result) -> None:
    """The result as ``.csv`` or ``.npz`` (module docstring), atomically."""
    if path.endswith(".csv"):
        return write_bytes(path, _csv_text(result).encode())
    arrays = {k: getattr(result, k) for k in ("t", "q", "qvel", "qacc", "tau_nm", "tension_n", "l_motor_m",
                                              "activation", "control", "control_clipped", "residual_nm",
                                              "root_qpos", "root_qvel", "root_qacc", "root_residual")}
    arrays = {k: v for k, v in arrays.items() if v is not None}
    arrays.update(status=status_names(result.status), status_code=status_codes(result.status),
                  joints=np.array(result.joints, dtype=str), muscles=np.array(result.muscles, dtype=str),
                  residual_dofs=np.array(result.residual_dofs, dtype=str), objective=np.array(result.objective),
                  root_dofs=np.array(result.root_dofs, dtype=str))
    write_npz(path, arrays)


def plot_activations(result, path: str, top: int = 8) -> None:
    """The ``top`` muscles by peak activation over time, frames not ``ok`` marked; written to ``path`` (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    values = result.activation if result.activation is not None else result.tension_n
    order = np.argsort(-np.nan_to_num(np.nanmax(np.abs(values), axis=0, initial=0.0)))[:top]
    fig, ax = plt.subplots(figsize=(9, 3.6), constrained_layout=True)
    for m in order:
        ax.plot(result.t, values[:, m], label=result.muscles[m].removesuffix("_tendon"))
    bad = ~result.ok
    if bad.any():
        ax.plot(result.t[bad], np.full(bad.sum(), 1.03 * np.nanmax(values[:, order], initial=1.0)), "k|",
                label="not ok")
    ax.set(xlabel="t [s]", ylabel="activation" if result.activation is not None else "tension [N]",
           title=f"muscle activations over the motion ({result.objective} objective)")
    ax.legend(fontsize=7, ncol=2)
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=110)
    plt.close(fig)
    write_bytes(path, buffer.getvalue(), "--plot")


def track_file(body, result, faults, args) -> str:
    """``--track``: the motion simulated by computed muscle control and open loop; the report's summary line."""
    from ..errors import BodySchemaInputError
    from ..statics.track import track_motion

    if result.root_qpos is not None:
        raise BodySchemaInputError("--track simulates a welded body; this motion moves a floating root (drop --track "
                                   "or the root's columns)")
    report = track_motion(body, result.t, result.q, result.qvel, result.qacc, faults,
                          control_step_s=args.control_step, residual_dofs=args.residual)
    return report.summary()
