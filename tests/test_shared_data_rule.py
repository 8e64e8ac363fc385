"""The ``shared_data`` rule: skip without ../shared/data on a developer's machine, fail under CI."""

from __future__ import annotations

import pytest

from tests.conftest import require_shared_data, shared_data_dir


def test_absent_data_skips_outside_ci(monkeypatch, tmp_path):
    missing = tmp_path / "no-such-data"
    monkeypatch.setenv("BLOCKLOC_SHARED_DATA", str(missing))
    monkeypatch.delenv("CI", raising=False)
    assert shared_data_dir() == missing
    with pytest.raises(pytest.skip.Exception, match="no-such-data"):
        require_shared_data(shared_data_dir())
    monkeypatch.setenv("CI", "false")
    with pytest.raises(pytest.skip.Exception):
        require_shared_data(shared_data_dir())


@pytest.mark.parametrize("value", ["true", "TRUE", "True"])
def test_absent_data_fails_under_ci(monkeypatch, tmp_path, value):
    missing = tmp_path / "no-such-data"
    monkeypatch.setenv("BLOCKLOC_SHARED_DATA", str(missing))
    monkeypatch.setenv("CI", value)
    with pytest.raises(pytest.fail.Exception, match="CI=true"):
        require_shared_data(shared_data_dir())


def test_present_data_is_returned(monkeypatch, tmp_path):
    (tmp_path / "data").mkdir()
    monkeypatch.setenv("BLOCKLOC_SHARED_DATA", str(tmp_path / "data"))
    for ci in ("true", ""):
        monkeypatch.setenv("CI", ci)
        assert require_shared_data(shared_data_dir()) == tmp_path / "data"


def test_default_location_is_beside_the_repo(monkeypatch):
    from tests.conftest import REPO

    monkeypatch.delenv("BLOCKLOC_SHARED_DATA", raising=False)
    assert shared_data_dir() == REPO.parent / "shared" / "data"
