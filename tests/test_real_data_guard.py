"""The real-data fixture: a missing folder under the data root skips; a missing root fails when CI requires data."""

import pytest


def test_missing_root_skips_unless_data_is_required(real_data, monkeypatch, tmp_path):
    monkeypatch.delenv("NRSFM_DATA", raising=False)
    monkeypatch.delenv("NRSFM_REQUIRE_DATA", raising=False)
    with pytest.raises(pytest.skip.Exception, match="NRSFM_DATA is not set"):
        real_data("h36m")
    monkeypatch.setenv("NRSFM_REQUIRE_DATA", "1")
    with pytest.raises(pytest.fail.Exception, match="NRSFM_REQUIRE_DATA=1"):
        real_data("h36m")
    monkeypatch.setenv("NRSFM_DATA", str(tmp_path / "nowhere"))
    with pytest.raises(pytest.fail.Exception, match="is not a folder"):
        real_data("h36m")


def test_missing_subfolder_skips_even_when_data_is_required(real_data, monkeypatch, tmp_path):
    (tmp_path / "h36m").mkdir()
    monkeypatch.setenv("NRSFM_DATA", str(tmp_path))
    monkeypatch.setenv("NRSFM_REQUIRE_DATA", "1")
    assert real_data("h36m") == tmp_path / "h36m"
    with pytest.raises(pytest.skip.Exception, match="has no surreal/sample"):
        real_data("surreal", "sample")
