"""The content-addressed result store: keys, atomic writes, corrupt entries."""

import warnings
from pathlib import Path

import numpy as np
import pytest

from resloc.experiments import store as store_mod
from resloc.experiments.config import default_scenario
from resloc.experiments.config_dump import scenario_to_dict
from resloc.experiments.store import (
    CorruptEntryWarning,
    ResultStore,
    canonical_json,
    cell_key,
    default_store,
)


def test_canonical_json_is_order_free_and_exact():
    a = canonical_json({"b": 1, "a": [0.1, 2.0], "c": np.float64(1e-300)})
    b = canonical_json({"c": 1e-300, "a": (0.1, 2), "b": np.int64(1)})
    assert a != b  # 2.0 and 2 are different values in a scenario
    assert a == canonical_json({"a": [0.1, 2.0], "c": 1e-300, "b": 1})
    assert canonical_json(float("nan")) == canonical_json(np.nan) != canonical_json(None)
    assert "0.30000000000000004" in canonical_json(0.1 + 0.2)  # repr, not rounded
    arr = canonical_json(np.arange(3, dtype=np.int8))
    assert "int8" in arr and arr != canonical_json(np.arange(3, dtype=np.int64))
    with pytest.raises(TypeError):
        canonical_json(object())


def test_cell_key_covers_scenario_seed_filter_and_version(monkeypatch):
    s = scenario_to_dict(default_scenario())
    k = cell_key("sim", scenario=s, trial=0, estimator="ckf")
    assert len(k) == 64 and k == cell_key("sim", scenario=s, trial=0, estimator="ckf")
    assert k != cell_key("sim", scenario=s, trial=1, estimator="ckf")
    assert k != cell_key("sim", scenario=s, trial=0, estimator="ekf")
    other = scenario_to_dict(default_scenario().replace(**{"detector.rho": 0.31}))
    assert k != cell_key("sim", scenario=other, trial=0, estimator="ckf")
    monkeypatch.setattr(store_mod, "__version__", "999.0")
    assert k != cell_key("sim", scenario=s, trial=0, estimator="ckf")


def test_cell_key_follows_the_source(monkeypatch, tmp_path):
    (tmp_path / "cl").mkdir()
    (tmp_path / "cl" / "step.py").write_text("x = 1\n")
    (tmp_path / "cl" / "cache.nbi").write_bytes(b"not a source")
    before = store_mod.fingerprint_sources(tmp_path)
    (tmp_path / "cl" / "cache.nbi").write_bytes(b"recompiled")
    assert store_mod.fingerprint_sources(tmp_path) == before  # caches are not sources
    (tmp_path / "cl" / "step.py").write_text("x = 2\n")
    edited = store_mod.fingerprint_sources(tmp_path)
    assert edited != before
    (tmp_path / "cl" / "step.py").rename(tmp_path / "step.py")  # same text, moved
    assert store_mod.fingerprint_sources(tmp_path) != edited
    # the installed package's own sources key every cell
    package = Path(store_mod.__file__).resolve().parents[1]
    assert store_mod.source_fingerprint() == store_mod.fingerprint_sources(package)
    k = cell_key("sim", trial=0)
    monkeypatch.setattr(store_mod, "source_fingerprint", lambda: "0" * 64)
    assert k != cell_key("sim", trial=0)


def test_put_get_roundtrip_and_atomic_layout(tmp_path):
    st = ResultStore(tmp_path / "st")
    key = cell_key("test", x=1)
    assert st.get(key) == (False, None) and key not in st
    value = {"series": np.linspace(0, 1, 5), "n": 3}
    path = st.put(key, value)
    assert path.parent.parent.name == "v1" and path.name == f"{key}.cell"
    hit, got = st.get(key)
    assert hit and got["n"] == 3 and np.array_equal(got["series"], value["series"])
    assert st.keys() == [key]
    assert not list(path.parent.glob("*.tmp"))  # no temporary file left behind
    st.put(key, {"n": 4})  # overwriting replaces in one rename
    assert st.get(key)[1] == {"n": 4}
    assert ResultStore(tmp_path / "st", read=False).get(key) == (False, None)  # --fresh


def test_an_interrupted_write_leaves_no_entry_and_no_temporary_file(tmp_path, monkeypatch):
    st = ResultStore(tmp_path / "st")
    key = cell_key("test", x=2)

    def interrupted(fd):
        raise KeyboardInterrupt  # Ctrl-C while the payload is being flushed to disk

    monkeypatch.setattr(store_mod.os, "fsync", interrupted)
    with pytest.raises(KeyboardInterrupt):
        st.put(key, {"n": 1})
    assert key not in st and not list((tmp_path / "st").rglob("*.tmp"))


@pytest.mark.parametrize("damage", ["flip", "truncate", "garbage"])
def test_corrupt_entry_is_detected_with_a_warning(tmp_path, damage):
    st = ResultStore(tmp_path)
    key = cell_key("test", damage=damage)
    path = st.put(key, {"values": list(range(100))})
    blob = bytearray(path.read_bytes())
    if damage == "flip":
        blob[-10] ^= 0xFF
    elif damage == "truncate":
        blob = blob[: len(blob) // 2]
    else:
        blob = bytearray(b"not a store entry")
    path.write_bytes(bytes(blob))
    with pytest.warns(CorruptEntryWarning, match="corrupt"):
        assert st.get(key) == (False, None)
    st.put(key, {"values": [1]})  # recomputed and written again
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert st.get(key) == (True, {"values": [1]})


def test_default_store_follows_the_environment(monkeypatch, tmp_path):
    monkeypatch.setenv("RESLOC_STORE", str(tmp_path / "elsewhere"))
    assert default_store() == tmp_path / "elsewhere"
    assert ResultStore().root == tmp_path / "elsewhere"
    monkeypatch.delenv("RESLOC_STORE")
    assert default_store() == store_mod.DEFAULT_STORE
