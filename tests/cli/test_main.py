"""The `hostd` command line itself: where the socket is, and usage errors (no daemon)."""

from __future__ import annotations

import pytest

from hostd.cli.main import main, socket_path


def test_the_socket_option_wins_over_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("HOSTD_SOCKET", "/env/hostd.sock")

    assert socket_path("/opt/hostd.sock") == "/opt/hostd.sock"
    assert socket_path(None) == "/env/hostd.sock"


def test_without_option_or_environment_the_default_path(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("HOSTD_SOCKET", raising=False)

    assert socket_path(None) == "/run/hostd/hostd.sock"


def test_no_command_is_a_usage_error(capsys: pytest.CaptureFixture[str]) -> None:
    assert main([]) == 2
    assert "usage: hostd" in capsys.readouterr().err


def test_an_unknown_option_is_a_usage_error_naming_the_command(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert main(["status", "--bogus"]) == 2
    assert "hostd status" in capsys.readouterr().err


def test_version_still_answers(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--version"]) == 0
    assert capsys.readouterr().out.startswith("hostd ")
