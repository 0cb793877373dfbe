"""The sensor log file: what it holds, what it refuses (one line each), and that noisy readings are data."""
from __future__ import annotations

import numpy as np
import pytest

from lightning_bodyschema.diagnosis import SensorLog, read_sensor_log, write_sensor_log
from lightning_bodyschema.errors import BodySchemaInputError

JOINTS, MUSCLES = ["shoulder", "elbow"], ["flexor", "extensor", "bi"]


def _rows(n=5, seed=0):
    rng = np.random.default_rng(seed)
    q, l_m = rng.uniform(-1, 1, (n, 2)), rng.uniform(0.3, 0.5, (n, 3))
    f = rng.uniform(0, 150, (n, 3))
    f[0, 0], f[1, 1] = -0.4, 151.0  # noisy readings of a slack and of a full muscle: kept as read
    return q, l_m, l_m + 1e-4, f + 1.0, f, np.array([3, 3, 7, 3, 7])


@pytest.mark.parametrize("ext", ["csv", "npz"])
def test_a_log_round_trips_grouped_by_case(tmp_path, ext):
    q, l_m, l_cmd, f_cmd, f, case = _rows()
    log = SensorLog.from_rows(JOINTS, MUSCLES, q, l_m, l_cmd, f_cmd, f, case, t_s=np.arange(5.0))
    path = str(tmp_path / f"log.{ext}")
    write_sensor_log(path, log)
    back = read_sensor_log(path, JOINTS, MUSCLES)
    assert back.cases.tolist() == [3, 7] and back.rows.sum(1).tolist() == [3, 2]
    np.testing.assert_array_equal(back.q_rad[back.rows], log.q_rad[log.rows])
    np.testing.assert_array_equal(back.f_n[0, :3, 0], [-0.4, f[1, 0], f[3, 0]])  # file order within a case
    assert back.f_n[0, 1, 1] == 151.0 and back.has_f.all()
    np.testing.assert_array_equal(back.t_s[1, :2], [2.0, 4.0])


def test_load_cells_may_be_missing_per_muscle(tmp_path):
    q, l_m, l_cmd, f_cmd, f, _ = _rows()
    f[:, 1] = np.nan
    path = str(tmp_path / "log.csv")
    write_sensor_log(path, SensorLog.from_rows(JOINTS, MUSCLES, q, l_m, l_cmd, f_cmd, f))
    assert "f_extensor" not in open(path).read()
    back = read_sensor_log(path, JOINTS, MUSCLES)
    assert back.has_f.tolist() == [True, False, True] and np.isnan(back.f_n[..., 1]).all()


def _write(tmp_path, header, rows):
    path = tmp_path / "bad.csv"
    path.write_text(",".join(header) + "\n" + "\n".join(",".join(map(str, r)) for r in rows) + "\n")
    return str(path)


def _header(drop=(), extra=()):
    cols = [f"q_{j}" for j in JOINTS] + [f"{p}{m}" for p in ("l_", "f_", "l_cmd_", "f_cmd_") for m in MUSCLES]
    return [c for c in cols if c not in drop] + list(extra)


def test_refusals_name_the_problem(tmp_path):
    with pytest.raises(BodySchemaInputError, match=r"missing column.*l_cmd_flexor"):
        read_sensor_log(_write(tmp_path, _header(drop=["l_cmd_flexor"]), [[0.1] * 13]), JOINTS, MUSCLES)
    header = _header(extra=["l_flexr"])
    with pytest.raises(BodySchemaInputError, match=r"'l_flexr'.*did you mean 'l_flexor'"):
        read_sensor_log(_write(tmp_path, header, [[0.1] * len(header)]), JOINTS, MUSCLES)
    rows = [[0.1] * 14, [0.1] * 14]
    rows[1][3] = "nan"
    with pytest.raises(BodySchemaInputError, match=r"'l_extensor' is NaN/inf in row 2 \(rows counted from 1"):
        read_sensor_log(_write(tmp_path, _header(), rows), JOINTS, MUSCLES)
    path = tmp_path / "mm.csv"
    path.write_text("# units: mm\n" + ",".join(_header()) + "\n" + ",".join(["1"] * 14) + "\n")
    with pytest.raises(BodySchemaInputError, match="units flag 'mm'"):
        read_sensor_log(str(path), JOINTS, MUSCLES)
