"""Settings from the environment (FIRP_SERVICE_*) and flags; the default bundle location."""

from __future__ import annotations

from pathlib import Path

import pytest
from pydantic import ValidationError

import firp
from service.__main__ import parse_args
from firp.core.bundle_format import shipped_bundle_dir
from service.settings import ServiceSettings


def test_the_default_bundle_is_the_shipped_one_of_the_task(monkeypatch):
    for name in ("FIRP_SERVICE_BUNDLE", "FIRP_SERVICE_TASK"):
        monkeypatch.delenv(name, raising=False)
    assert ServiceSettings().bundle_dir == Path(firp.__file__).resolve().parents[1] / "models" / "stacking"
    assert ServiceSettings(task="replacement").bundle_dir == shipped_bundle_dir("replacement")
    assert ServiceSettings(bundle="/b", task="replacement").bundle_dir == Path("/b")


def test_environment_is_read_with_the_prefix(monkeypatch):
    monkeypatch.setenv("FIRP_SERVICE_BUNDLE", "/srv/bundle")
    monkeypatch.setenv("FIRP_SERVICE_PORT", "9100")
    monkeypatch.setenv("FIRP_SERVICE_API_KEY", "sup3r-s3cret")
    monkeypatch.setenv("FIRP_SERVICE_THREADS", "2")
    s = ServiceSettings()
    assert (s.bundle_dir, s.port, s.threads) == (Path("/srv/bundle"), 9100, 2)
    assert s.api_key.get_secret_value() == "sup3r-s3cret" and "sup3r" not in repr(s)  # a secret stays out of logs


def test_flags_override_the_environment_and_only_given_flags_count(monkeypatch):
    monkeypatch.setenv("FIRP_SERVICE_PORT", "9100")
    monkeypatch.setenv("FIRP_SERVICE_HOST", "0.0.0.0")
    flags = parse_args(["--port", "8002", "--bundle", "/b", "--threads", "3", "--no-access-log"])
    assert flags == {"port": 8002, "bundle": Path("/b"), "threads": 3, "access_log": False}
    s = ServiceSettings(**flags)
    assert (s.port, s.host, s.bundle, s.threads, s.access_log) == (8002, "0.0.0.0", Path("/b"), 3, False)


@pytest.mark.parametrize("bad", [{"port": 70000}, {"threads": 0}, {"min_image_side": 500, "max_image_side": 100},
                                 {"max_aspect_ratio": 0.5}, {"unknown": 1}])
def test_bad_settings_are_refused_at_start(bad):
    with pytest.raises(ValidationError):
        ServiceSettings(**bad)
