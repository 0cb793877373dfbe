"""The exported AOTInductor package: equals Python from ONE export, refuses what it cannot serve, and the C++
example matches it. Slow: the session's export compiles for a minute or more, the C++ build as long."""
import json
import os
import stat
import subprocess

import numpy as np
import pytest
import torch

from physics_checks import spring_length_tol

from lightning_bodyschema.adaptation.command import AdaptationResult
from lightning_bodyschema.deploy import STATUS_CODES, file_sha256, load_exported
from lightning_bodyschema.deploy.module import FAULT_TOL_M
from lightning_bodyschema.errors import BodySchemaInputError
from lightning_bodyschema.faults import Faults
from lightning_bodyschema.npz import default_file_mode

pytestmark = pytest.mark.slow
REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def test_package_equals_python_on_mixed_faults(package, diff60, mixed_cases):
    schema = diff60[0]
    q, faults = mixed_cases
    ref = schema.adapter(faults, n_steps=20, check_physics=False)(q)
    got = load_exported(package, schema.robot_model.muscle_names, schema.robot_model.joint_names,
                        expected_sha256=file_sha256(package))(q, faults)
    ok = got.status == "ok"
    assert ok.sum() >= 30 and (got.status == ref.status).all()  # the same status on every case
    np.testing.assert_allclose(got.l_motor_m[ok], ref.l_motor_m[ok], rtol=0, atol=1e-6)
    np.testing.assert_allclose(got.f_n[ok], ref.f_n[ok], rtol=0, atol=2e-3)
    not_met = got.status == "fault_not_met"  # a band above its jam: the command breaks one of them
    broken = np.maximum(ref.diagnostics["band_violation_m"], ref.diagnostics["jam_violation_m"])
    assert not_met.any()
    assert (got.status[~ok] == "fault_not_met").all() and (broken[not_met] > FAULT_TOL_M).all()
    assert np.isnan(got.l_motor_m[~ok]).all() and np.isnan(got.f_n[~ok]).all()
    one = load_exported(package)(q[:1], faults.take([0]))  # batch 1 from the same (dynamic) package
    np.testing.assert_allclose(one.l_motor_m, got.l_motor_m[:1], rtol=0, atol=1e-6)


def test_metadata_names_units_codes_and_checkpoint(package, diff60):
    meta = load_exported(package).metadata
    robot = diff60[0].robot_model
    assert meta["muscle_names"] == list(robot.muscle_names) and meta["joint_names"] == list(robot.joint_names)
    assert meta["status_codes"] == STATUS_CODES and meta["checkpoint_sha256"] == "test-session"
    assert meta["n_steps"] == 20 and meta["units"]["l_motor_m"] == "m" and meta["spring"]["k_n"] == 1000.0
    assert meta["schema_class"].endswith("DiffusionSchema") and meta["schema_kind"] == "diffusion"
    # readable as open() would have made it (0644 under umask 022), not mkstemp's 0600: a controller running as
    # another user must read it
    assert stat.S_IMODE(os.stat(package).st_mode) == default_file_mode()


def test_bad_values_are_a_bad_input_status_never_an_ok_command(package, diff60, mixed_cases):
    q, faults = mixed_cases
    adapter = load_exported(package)
    tensors = [t.clone() for t in adapter.inputs(q[:8], faults.take(np.arange(8)))]
    tensors[0][0, 0] = float("nan")  # NaN posture
    tensors[0][1, 1] = 10.0  # outside the joint range
    tensors[2][2, 0], tensors[3][2, 0] = 1.0, float("nan")  # a jam without its length
    tensors[4][3, 1] = -5.0  # a negative tension limit
    tensors[1][4, :] = 1.0  # every muscle cut
    tensors[5][5, 2], tensors[6][5, 2] = 0.2, 0.1  # a band with lo > hi
    tensors[1][6, 3] = 0.5  # a mask that is neither 0 nor 1
    l_motor, f, status = adapter.run(*tensors)
    assert (status[:7].numpy() == STATUS_CODES["bad_input"]).all()
    assert torch.isnan(l_motor[:7]).all() and torch.isnan(f[:7]).all()
    alone = adapter(q[7:8], faults.take([7]))  # the good case next to them is untouched
    np.testing.assert_allclose(l_motor[7].numpy(), alone.l_motor_m[0], rtol=0, atol=1e-6)


def test_wrong_shapes_and_another_robot_are_refused(package, diff60, mixed_cases):
    q, faults = mixed_cases
    adapter = load_exported(package)
    with pytest.raises(BodySchemaInputError, match="q_ref has shape"):
        adapter(np.zeros((2, 3)), Faults.none(2, 6))
    with pytest.raises(BodySchemaInputError, match="faults have shape"):
        adapter(q[:2], Faults.none(2, 8))
    with pytest.raises(BodySchemaInputError, match="another robot"):
        load_exported(package, muscle_names=[f"m{i}" for i in range(8)])
    with pytest.raises(BodySchemaInputError, match="another robot"):
        load_exported(package, joint_names=["shoulder"])


def test_truncated_or_corrupt_package_is_one_clear_error(package, tmp_path):
    data = open(package, "rb").read()
    truncated, garbage = tmp_path / "truncated.pt2", tmp_path / "garbage.pt2"
    truncated.write_bytes(data[: len(data) // 2])
    garbage.write_bytes(b"not a package" * 100)
    for path in (truncated, garbage):
        with pytest.raises(BodySchemaInputError, match="corrupt or truncated"):
            load_exported(str(path))
    with pytest.raises(BodySchemaInputError, match="no adapter package"):
        load_exported(str(tmp_path / "missing.pt2"))


def _adapt_once(build, *args):
    return subprocess.run([str(build / "adapt_once"), *args], capture_output=True, text=True, timeout=120)


def test_cpp_adapt_once_matches_python(package, cpp_build, diff60):
    schema = diff60[0]
    names = schema.robot_model.muscle_names
    cases = [((0.3, -0.2), ["shoulder_flexor"], {"elbow_flexor": 0.151}),
             ((-0.1, 0.4), [], {}),
             ((0.2, 0.1), ["biarticular_flexor", "elbow_extensor"], {}),
             ((0.0, 0.3), [], {"shoulder_extensor": 0.17, "elbow_flexor": 0.14})]
    for q, cut, jam in cases:
        args = [package, "--q", ",".join(map(str, q))]
        args += ["--cut", ",".join(cut)] if cut else []
        args += ["--jam", ",".join(f"{m}={v}" for m, v in jam.items())] if jam else []
        run = _adapt_once(cpp_build, *args)
        assert run.returncode == 0, run.stderr
        got = json.loads(run.stdout.replace("NaN", "null"))
        ref = schema.adapter(Faults.from_names(names, cut=[cut], jam=[jam]), n_steps=20, check_physics=False)(
            np.array([q]))
        assert got["status"] == ref.status[0]
        if got["status"] == "ok":
            np.testing.assert_allclose(got["l_motor_m"], ref.l_motor_m[0], rtol=0, atol=1e-6)
            np.testing.assert_allclose(got["f_n"], ref.f_n[0], rtol=0, atol=2e-3)


def test_cpp_refuses_corrupt_packages_and_unknown_muscles(package, cpp_build, tmp_path):
    truncated = tmp_path / "truncated.pt2"
    truncated.write_bytes(open(package, "rb").read()[:4096])
    run = _adapt_once(cpp_build, str(truncated), "--q", "0.1,0.1")
    assert run.returncode == 1 and "cannot load adapter package" in run.stderr
    run = _adapt_once(cpp_build, package, "--q", "0.1,0.1", "--cut", "tail_flexor")
    assert run.returncode == 1 and "unknown muscle 'tail_flexor'" in run.stderr  # a fault for another robot
    run = _adapt_once(cpp_build, package, "--q", "nan,0.1")
    assert run.returncode == 0 and json.loads(run.stdout.replace("NaN", "null"))["status"] == "bad_input"
    loop = subprocess.run([str(cpp_build / "control_loop"), package, "--ticks", "200", "--json", "--sha256",
                           file_sha256(package).upper()], capture_output=True, text=True, timeout=300)
    assert loop.returncode == 0, loop.stderr
    assert json.loads(loop.stdout)["ok_ticks"] == 200
    assert json.loads(loop.stdout)["program"] == "batch1"  # one case per tick: the dynamic package's batch-1 program
    forged = tmp_path / "forged.pt2"  # one byte changed: refused by its digest before it is loaded
    data = bytearray(open(package, "rb").read())
    data[len(data) // 2] ^= 1
    forged.write_bytes(bytes(data))
    for program, extra in (("adapt_once", ["--q", "0.1,0.1"]), ("control_loop", ["--ticks", "5"])):
        run = subprocess.run([str(cpp_build / program), str(forged), *extra, "--sha256", file_sha256(package)],
                             capture_output=True, text=True, timeout=120)
        assert run.returncode == 1 and "refused unloaded" in run.stderr and run.stderr.count("\n") == 1


def test_structured_package_equals_python_in_python_and_cpp(struct_package, struct30, struct_cases, cpp_build):
    """The structured schema's package: Python's statuses on every case and its ok commands (1e-5 m, 1e-2 N), from
    load_exported and from the unchanged C++ example."""
    q, faults = struct_cases
    ref = struct30.adapter(faults, check_physics=False)(q)
    adapter = load_exported(struct_package, expected_sha256=file_sha256(struct_package))
    rows = [adapter(q[i:i + 1], faults.take([i])) for i in range(len(q))]  # a batch-1 package: one call per case
    got = AdaptationResult(*(np.concatenate([getattr(r, k) for r in rows]) for k in ("l_motor_m", "f_n", "status")))
    assert adapter.kind == "structured" and adapter.metadata["schema_class"].endswith("StructuredSchema")
    assert adapter.metadata["programs"] == 1 and list(adapter.programs) == ["1"]  # a static export: one program
    ok = got.status == "ok"
    assert (got.status == ref.status).all() and 5 <= ok.sum() < len(q)
    np.testing.assert_allclose(got.l_motor_m[ok], ref.l_motor_m[ok], rtol=0, atol=1e-5)
    np.testing.assert_allclose(got.f_n[ok], ref.f_n[ok], rtol=0, atol=1e-2)
    names = struct30.robot_model.muscle_names
    for i in range(6):
        args = [struct_package, "--q", ",".join(repr(float(v)) for v in q[i]), "--sha256", file_sha256(struct_package)]
        args += ["--cut", ",".join(names[j] for j in np.flatnonzero(faults.cut[i]))] if faults.cut[i].any() else []
        jam = [f"{names[j]}={float(faults.l_fixed_m[i, j])!r}" for j in np.flatnonzero(faults.fix[i])]
        args += ["--jam", ",".join(jam)] if jam else []
        weak = [f"{names[j]}={float(faults.f_max_n[i, j])!r}" for j in np.flatnonzero(faults.weak[i])]
        args += ["--weak", ",".join(weak)] if weak else []
        band = [f"{names[j]}={float(faults.l_band_m[i, j, 0])!r}:{float(faults.l_band_m[i, j, 1])!r}"
                for j in np.flatnonzero(faults.band[i])]
        args += ["--band", ",".join(band)] if band else []
        run = _adapt_once(cpp_build, *args)
        assert run.returncode == 0, run.stderr
        line = json.loads(run.stdout.replace("NaN", "null"))
        assert line["status"] == ref.status[i]
        if line["status"] == "ok":
            np.testing.assert_allclose(line["l_motor_m"], ref.l_motor_m[i], rtol=0, atol=1e-5)
            np.testing.assert_allclose(line["f_n"], ref.f_n[i], rtol=0, atol=1e-2)
    run = _adapt_once(cpp_build, struct_package, "--q", "0.1,0.1", "--cut", "tail_flexor")
    assert run.returncode == 1 and "unknown muscle 'tail_flexor'" in run.stderr and run.stderr.count("\n") == 1
    # the control loop's sweep: the same ok ticks with its reusing CPU allocator (the default) and the system's
    loops = [subprocess.run([str(cpp_build / "control_loop"), struct_package, "--ticks", "300", "--json", *extra],
                            capture_output=True, text=True, timeout=300) for extra in ([], ["--system-allocator"])]
    assert all(loop.returncode == 0 for loop in loops), [loop.stderr for loop in loops]
    assert json.loads(loops[0].stdout)["ok_ticks"] == json.loads(loops[1].stdout)["ok_ticks"] > 0
    assert {json.loads(loop.stdout)["program"] for loop in loops} == {"model"}
    with pytest.raises(BodySchemaInputError, match="unknown muscle 'tail_flexor'"):
        Faults.from_names(adapter.muscle_names, cut=[["tail_flexor"]])
    with pytest.raises(BodySchemaInputError, match="another robot"):
        load_exported(struct_package, muscle_names=names[::-1])


def test_per_muscle_package_equals_python_at_any_batch(paths_package, struct_paths, paths_cases):
    """A per-muscle body's package (the body from its frozen snapshot, a dynamic batch): Python's statuses and ok
    commands (the package's contract, 1e-5 m and 1e-2 N) on every case in one call, and on one case alone."""
    q, faults = paths_cases
    ref = struct_paths.adapter(faults, check_physics=False)(q)
    adapter = load_exported(paths_package, expected_sha256=file_sha256(paths_package))
    for rows in (np.arange(len(q)), np.arange(1)):
        got, ok = adapter(q[rows], faults.take(rows)), ref.status[rows] == "ok"
        assert (got.status == ref.status[rows]).all() and (len(rows) == 1 or 5 <= ok.sum() < len(q))
        np.testing.assert_allclose(got.l_motor_m[ok], ref.l_motor_m[rows][ok], rtol=0, atol=1e-5)
        np.testing.assert_allclose(got.f_n[ok], ref.f_n[rows][ok], rtol=0, atol=1e-2)
        assert np.isnan(got.l_motor_m[~ok]).all() and np.isnan(got.f_n[~ok]).all()


def _by_program(adapter, key, tensors, rows):
    """``adapter``'s program ``key`` on ``rows`` of ``tensors`` (the package's inputs), one call per case for a
    static batch-1 program: (l_motor_m, f_n, status) as numpy."""
    program = adapter.programs[key]
    calls = [[t[r:r + 1] for t in tensors[:-1]] for r in rows] if key == "1" else [[t[rows] for t in tensors[:-1]]]
    outs = [program(*call, tensors[-1]) for call in calls]
    return tuple(torch.cat([out[k] for out in outs]).numpy() for k in range(3))


@pytest.mark.parametrize("which, atol_m, atol_n", [("package", 1e-6, 2e-3), ("paths_package", 1e-5, 1e-2)])
def test_dynamic_package_holds_a_batch1_program_that_answers_alike(request, which, atol_m, atol_n):
    """A dynamic export holds the dynamic program and a static batch-1 one (dispatched to for one case): the same
    statuses and ok commands (the package's tolerances) at batch 1 and at batch 7."""
    path = request.getfixturevalue(which)
    cases = request.getfixturevalue("mixed_cases" if which == "package" else "paths_cases")
    adapter = load_exported(path)
    assert adapter.metadata["programs"] == "dynamic,1" and list(adapter.programs) == ["dynamic", "1"]
    assert adapter.program_for(1) == "1" and adapter.program_for(7) == adapter.program_for(2) == "dynamic"
    tensors = adapter.inputs(cases[0][:7], cases[1].take(np.arange(7)))
    for rows in (np.arange(1), np.arange(7)):
        l_dyn, f_dyn, s_dyn = _by_program(adapter, "dynamic", tensors, rows)
        l_one, f_one, s_one = _by_program(adapter, "1", tensors, rows)
        ok = s_dyn == STATUS_CODES["ok"]
        assert (s_one == s_dyn).all() and (len(rows) == 1 or ok.any())
        np.testing.assert_allclose(l_one[ok], l_dyn[ok], rtol=0, atol=atol_m)
        np.testing.assert_allclose(f_one[ok], f_dyn[ok], rtol=0, atol=atol_n)
        assert np.isnan(l_one[~ok]).all() and np.isnan(f_one[~ok]).all()


def test_a_package_written_with_one_program_still_loads_and_runs(legacy_package, struct_package, struct_cases,
                                                                  cpp_build):
    """A package from before the batch-1 program (one "model" program, no "programs" metadata) answers as the
    static package of the same schema, in Python and C++ (which run its only program)."""
    q, faults = struct_cases
    legacy, static = load_exported(legacy_package), load_exported(struct_package)
    assert "programs" not in legacy.metadata and list(legacy.programs) == ["1"] and legacy.program_for(1) == "1"
    for i in range(6):
        got, ref = legacy(q[i:i + 1], faults.take([i])), static(q[i:i + 1], faults.take([i]))
        assert got.status[0] == ref.status[0]
        # the same exported program compiled twice: a few roundings at the lengths' scale at most
        np.testing.assert_allclose(got.l_motor_m, ref.l_motor_m, rtol=0, atol=spring_length_tol(ref.l_motor_m))
    loop = subprocess.run([str(cpp_build / "control_loop"), legacy_package, "--ticks", "50", "--json"],
                          capture_output=True, text=True, timeout=300)
    assert loop.returncode == 0 and json.loads(loop.stdout)["program"] == "model", loop.stderr
