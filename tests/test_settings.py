"""Settings: defaults < ARTICAST_* environment < command line; bad values are one clear error."""

import argparse

import pytest

from articast.core.errors import InputError
from articast.service.settings import (
    HubSettings,
    ServerSettings,
    add_arguments,
    from_args,
    from_env,
)


def test_env_then_overrides():
    env = {"ARTICAST_PORT": "9000", "ARTICAST_HOST": "0.0.0.0"}
    s = from_env(ServerSettings, env)
    assert (s.host, s.port) == ("0.0.0.0", 9000)
    assert from_env(ServerSettings, env, port=1234, host=None).port == 1234


def test_bad_env_value_names_the_variable():
    with pytest.raises(InputError, match="ARTICAST_MAX_QUEUE"):
        from_env(HubSettings, {"ARTICAST_MAX_QUEUE": "lots"})


def test_cli_mirrors_every_field(monkeypatch):
    p = argparse.ArgumentParser()
    add_arguments(p, HubSettings)
    monkeypatch.setenv("ARTICAST_MAX_QUEUE", "7")
    monkeypatch.setenv("ARTICAST_STALL_TIMEOUT_S", "3.5")
    s = from_args(HubSettings, p.parse_args(["--max-queue", "9"]))
    assert s.max_queue == 9 and s.stall_timeout_s == 3.5
    assert HubSettings().max_queue == 4
