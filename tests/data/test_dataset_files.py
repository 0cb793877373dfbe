"""Dataset files: byte-deterministic, and a cache that is stale, tampered with or truncated is rebuilt, never used."""
import numpy as np
import pytest

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


def test_large_arrays_stream_to_the_same_bytes(tmp_path, monkeypatch):
    """Arrays over ``STREAM_BYTES`` go to the file in slices; the archive is byte for byte the one written whole."""
    from lightning_bodyschema import npz

    rng = np.random.default_rng(0)
    arrays = {"q": rng.random((300, 7)), "ok": rng.random(1001) > 0.5, "xml": np.array("<mujoco/>"),
              "fortran": np.asfortranarray(rng.random((40, 30))), "n": np.array(3)}
    save_npz(str(tmp_path / "whole.npz"), **arrays)
    monkeypatch.setattr(npz, "STREAM_BYTES", 100)  # every plain array above 100 bytes streams, in 100-byte slices
    save_npz(str(tmp_path / "sliced.npz"), **arrays)
    assert (tmp_path / "sliced.npz").read_bytes() == (tmp_path / "whole.npz").read_bytes()
    back = load_npz(str(tmp_path / "sliced.npz"))
    assert all(np.array_equal(back[name], value) for name, value in arrays.items())
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sliced.npz", "whole.npz"]  # no temp file left


def test_cache_key_does_not_depend_on_workers(arm, tmp_path, monkeypatch):
    """A dataset cached by a run on one process is the one a run on several reads back (the same bytes)."""
    from lightning_bodyschema.data import dataset

    first = load_or_build_dataset(arm, 100, 3, SpringParams(), cache_dir=str(tmp_path), workers=1)
    monkeypatch.setattr(dataset, "build_dataset", lambda *a, **k: pytest.fail("the cache was not used"))
    again = load_or_build_dataset(arm, 100, 3, SpringParams(), cache_dir=str(tmp_path), workers=4)
    np.testing.assert_array_equal(again["l_motor"], first["l_motor"])
