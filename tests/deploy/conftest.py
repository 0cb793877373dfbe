"""One exported adapter package per test session (compiling it takes 1-2+ minutes on the shared CPU)."""
import os
import shutil
import subprocess

import pytest
import torch

from physics_checks import mixed_faults, train_schema

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


@pytest.fixture(scope="session")
def mixed_cases(diff60, dm):
    """(q_ref, faults): 42 cases of cut, jammed, weakened and banded muscles (some bands empty under their jam)."""
    return mixed_faults(diff60[0], dm, n=42)


@pytest.fixture(scope="session")
def struct30(dm):
    """A small StructuredSchema of the paper arm (2 x 64 SiLU, 30 epochs, float32): ok and infeasible_learned rows."""
    from lightning_bodyschema.schemas import StructuredSchema

    return train_schema(StructuredSchema, 30, dm, hidden=64, n_hidden=2, batch_size=64)[0]


@pytest.fixture(scope="session")
def struct_cases(struct30, dm):
    """(q_ref, faults): 42 mixed cases (cut, jammed, weakened, banded; some bands above their jam) for struct30."""
    return mixed_faults(struct30, dm, n=42)


@pytest.fixture(scope="session")
def struct_paths(dm):
    """A per-muscle StructuredSchema of the paper arm (configs/myoarm.yaml's kind: polynomial paths, two branches and
    a gate, cells, the gravity tree's torque; least squares, one epoch): its package evaluates the BodySnapshot."""
    from physics_checks import fit_structured

    return fit_structured(dm, length_model="per_muscle", path_degree=8, torque_model="gravity", path_branches=2,
                          path_cells=2)[0]


@pytest.fixture(scope="session")
def struct_poly(dm):
    """A per-muscle StructuredSchema of the paper arm with a polynomial torque (configs/myoelbow.yaml's kind): no
    BodySnapshot covers it, so its package evaluates ``schema.body``."""
    from physics_checks import fit_structured

    return fit_structured(dm, length_model="per_muscle", path_degree=8, torque_model="polynomial")[0]


@pytest.fixture(scope="session")
def poly_cases(struct_poly, dm):
    """(q_ref, faults): 42 mixed cases for struct_poly."""
    return mixed_faults(struct_poly, dm, n=42)


@pytest.fixture(scope="session")
def paths_cases(struct_paths, dm):
    """(q_ref, faults): 42 mixed cases for struct_paths."""
    return mixed_faults(struct_paths, dm, n=42)


@pytest.fixture(scope="session")
def paths_package(struct_paths, tmp_path_factory):
    """struct_paths' adapter package for a dynamic batch (its BodySnapshot evaluates every case of a call at once)."""
    from lightning_bodyschema.deploy import export_package

    path = str(tmp_path_factory.mktemp("deploy") / "per_muscle.pt2")
    return export_package(struct_paths, path, batch="dynamic", ckpt_sha256="test-session")


@pytest.fixture(scope="session")
def struct_package(struct30, tmp_path_factory):
    """struct30's adapter package for batch 1 (what a control loop sends, and what the C++ example runs)."""
    from lightning_bodyschema.deploy import export_package

    path = str(tmp_path_factory.mktemp("deploy") / "structured.pt2")
    return export_package(struct30, path, batch=1, ckpt_sha256="test-session")


@pytest.fixture(scope="session")
def legacy_package(struct30, tmp_path_factory):
    """struct30's batch-1 package as written before packages held several programs: one program, no "programs"
    metadata (aoti_compile_and_package, as the export then called it)."""
    from lightning_bodyschema.deploy.package import exported_program, package_metadata, package_module

    module = package_module(struct30).eval()
    metadata = package_metadata(struct30, module, "test-session", 1)
    del metadata["programs"]
    path = str(tmp_path_factory.mktemp("deploy") / "legacy.pt2")
    return torch._inductor.aoti_compile_and_package(exported_program(module, 1), package_path=path,
                                                    inductor_configs={"aot_inductor.metadata": metadata})


@pytest.fixture(scope="session")
def package(diff60, tmp_path_factory):
    """The briefly trained paper-arm diffusion schema's adapter package (20 steps, dynamic batch)."""
    from lightning_bodyschema.deploy import export_package

    path = str(tmp_path_factory.mktemp("deploy") / "adapter.pt2")
    return export_package(diff60[0], path, 20, "dynamic", ckpt_sha256="test-session")


@pytest.fixture(scope="session")
def cpp_build(tmp_path_factory):
    """The examples/cpp programs built against the installed torch (skipped without cmake or a C++ compiler)."""
    missing = [tool for tool in ("cmake", "c++") if shutil.which(tool) is None]
    if missing:
        pytest.skip(f"no {' and '.join(missing)} on this machine: the C++ example cannot be built")
    build = tmp_path_factory.mktemp("cpp_build")
    generator = ["-G", "Ninja"] if shutil.which("ninja") else []
    subprocess.run(["cmake", "-S", os.path.join(REPO, "examples", "cpp"), "-B", str(build), *generator,
                    f"-DCMAKE_PREFIX_PATH={torch.utils.cmake_prefix_path}"], check=True, capture_output=True)
    subprocess.run(["cmake", "--build", str(build)], check=True, capture_output=True)
    return build
