import json

import pytest

from protocols.results import CurvePoint, RunResult, config_hash, find_results, read_result, write_result


def test_roundtrip_and_atomic(tmp_path):
    r = RunResult(method="softmax_gs", dataset="patterns", scene="circle4", budget="cap", seed=0,
                  metrics={"psnr": 28.1}, curve=[CurvePoint(10, 1.5, 20.0, 4)])
    p = write_result(tmp_path / "run", r)
    assert read_result(p) == r
    assert find_results(tmp_path) == [p]
    assert [f.name for f in p.parent.iterdir()] == ["results.json"]  # no temp file left


def test_interrupted_write_keeps_previous(tmp_path, monkeypatch):
    r = RunResult(method="3dgs", dataset="d", scene="s", budget="full", seed=0)
    p = write_result(tmp_path, r)
    before = p.read_text()
    import smgs.atomic as pr

    def boom(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(pr.os, "replace", boom)
    with pytest.raises(KeyboardInterrupt):
        write_result(tmp_path, RunResult(method="x", dataset="d", scene="s", budget="full", seed=1))
    assert p.read_text() == before
    assert sorted(f.name for f in tmp_path.iterdir()) == ["results.json"]


def test_bad_file_names_the_path(tmp_path):
    p = tmp_path / "results.json"
    p.write_text(json.dumps({"method": "a", "bogus": 1}))
    with pytest.raises(ValueError, match="results.json"):
        read_result(p)


def test_config_hash_ignores_key_order():
    assert config_hash({"a": 1, "b": {"c": 2}}) == config_hash({"b": {"c": 2}, "a": 1})
    assert config_hash({"a": 1}) != config_hash({"a": 2})
