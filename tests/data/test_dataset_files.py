"""Dataset files: byte-deterministic, and a cache that is stale, tampered with or truncated is rebuilt, never used."""
import numpy as np

from lightning_bodyschema.apps.dataset_tool import make_dataset_main
from lightning_bodyschema.data.dataset import load_or_build_dataset
from lightning_bodyschema.data.recorded import read_recorded
from lightning_bodyschema.npz import load_npz, save_npz
from lightning_bodyschema.sim import SpringParams


def test_same_seed_same_bytes_other_seed_other_bytes(tmp_path):
    paths = {}
    for name, seed in (("a", 0), ("b", 0), ("c", 1)):
        paths[name] = tmp_path / f"{name}.npz"
        make_dataset_main(["--model", "paper_arm", "--n", "200", "--seed", str(seed), "--out", str(paths[name])])
    assert paths["a"].read_bytes() == paths["b"].read_bytes()
    assert paths["a"].read_bytes() != paths["c"].read_bytes()
    table = read_recorded(str(paths["a"]))  # the recorded-data format: q_<joint>, l_<muscle>, f_<muscle> columns
    assert table.q.shape == (200, 2) and table.f.shape == (200, 6) and table.joints == ["shoulder", "elbow"]
    assert "<mujoco" in str(load_npz(str(paths["a"]))["meta_model_xml"])


def _cache_file(tmp_path):
    files = list(tmp_path.glob("equilibrium-*.npz"))
    assert len(files) == 1
    return files[0]


def test_tampered_stale_or_truncated_cache_is_rebuilt(arm, tmp_path):
    spring = SpringParams()
    fresh = load_or_build_dataset(arm, 100, 3, spring, cache_dir=str(tmp_path))
    path = _cache_file(tmp_path)
    good = path.read_bytes()

    arrays = load_npz(str(path))
    arrays["f"] = arrays["f"] + 1.0  # tampered samples, key and digest left as they were
    save_npz(str(path), **arrays)
    again = load_or_build_dataset(arm, 100, 3, spring, cache_dir=str(tmp_path))
    np.testing.assert_array_equal(again["f"], fresh["f"])
    assert path.read_bytes() == good  # rewritten with the true data

    arrays = load_npz(str(path))
    arrays["cache_key"] = np.array("0" * 64)  # stale: made by other settings
    save_npz(str(path), **arrays)
    np.testing.assert_array_equal(load_or_build_dataset(arm, 100, 3, spring, cache_dir=str(tmp_path))["q"], fresh["q"])
    assert path.read_bytes() == good

    path.write_bytes(good[: len(good) // 2])  # truncated
    np.testing.assert_array_equal(load_or_build_dataset(arm, 100, 3, spring, cache_dir=str(tmp_path))["l_motor"],
                                  fresh["l_motor"])
    assert path.read_bytes() == good
