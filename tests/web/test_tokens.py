"""Tokens on disk, the `[web]` table, and `hostd token`."""

from __future__ import annotations

import os
import pwd
import stat
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

from hostd.api.tokens import TokenStore
from hostd.cli.main import main
from hostd.config import ConfigError, parse_config


def test_a_token_is_kept_only_as_its_hash_in_a_private_file(tmp_path: Path) -> None:
    store = TokenStore(tmp_path)
    token = store.create("bench")
    text = store.path.read_text()
    assert token not in text and store.records()[0].sha256 in text
    # The service's user and group read it; nobody else.
    assert stat.S_IMODE(store.path.stat().st_mode) == 0o640
    assert store.verify(token) and not store.verify(token + "x") and not store.verify(None)


def test_a_token_made_or_revoked_elsewhere_counts_at_once(tmp_path: Path) -> None:
    daemon, cli = TokenStore(tmp_path), TokenStore(tmp_path)
    token = cli.create()
    assert daemon.verify(token)
    assert cli.revoke(cli.records()[0].id)
    assert not daemon.verify(token)


def test_without_a_web_table_there_is_no_web_server() -> None:
    assert parse_config({}).web is None
    web = parse_config({"web": {"listen": "[::1]:7080"}}).web
    assert web is not None and (web.host, web.port, web.control) == ("::1", 7080, True)
    for bad in ("7080", "localhost:", "host:99999"):
        with pytest.raises(ConfigError, match=r"web\.listen"):
            parse_config({"web": {"listen": bad}})


def test_hostd_token_create_prints_a_token_the_daemon_accepts(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    config = tmp_path / "hostd.toml"
    config.write_text(f'[daemon]\nstate_dir = "{tmp_path / "state"}"\n')
    assert main(["token", "create", "--config", str(config), "--name", "phone"]) == 0
    token = capsys.readouterr().out.strip()
    assert TokenStore(tmp_path / "state").verify(token)
    assert main(["token", "list", "--config", str(config)]) == 0
    assert "phone" in capsys.readouterr().out
    assert main(["token", "revoke", "--config", str(config), "nope"]) == 1


def test_token_create_as_root_leaves_a_file_the_service_user_reads() -> None:
    # Not under tmp_path: pytest's base directory is root's alone, the service user
    # could not even reach the state directory.
    with tempfile.TemporaryDirectory(prefix="hostd-token-") as where:
        os.chmod(where, 0o755)
        token_create_as_root(Path(where))


def token_create_as_root(tmp_path: Path) -> None:
    """`sudo hostd token create` (docs/web.md): the file goes to the state directory's
    owner and group (the service's, by StateDirectory=), so its logins work."""
    assert os.geteuid() == 0, "this test runs as root, as `sudo hostd token create` does"
    service = pwd.getpwnam("nobody")
    state = tmp_path / "state"
    state.mkdir(mode=0o750)
    os.chown(state, service.pw_uid, service.pw_gid)
    config = tmp_path / "hostd.toml"
    config.write_text(f'[daemon]\nstate_dir = "{state}"\n')
    config.chmod(0o644)
    made = subprocess.run(
        [sys.executable, "-m", "hostd", "token", "create", "--config", str(config)],
        capture_output=True,
        text=True,
        check=True,
        preexec_fn=lambda: os.umask(0o077),  # a root with a strict umask, too
    )
    token = made.stdout.strip()
    st = (state / "web-tokens.json").stat()
    assert (st.st_uid, st.st_gid) == (service.pw_uid, service.pw_gid)
    assert stat.S_IMODE(st.st_mode) == 0o640
    # As the service's user (it used to be a PermissionError: HTTP 500 on every login).
    as_service = subprocess.run(
        [
            "setpriv",
            f"--reuid={service.pw_uid}",
            f"--regid={service.pw_gid}",
            "--clear-groups",
            "cat",
            str(state / "web-tokens.json"),
        ],
        capture_output=True,
        check=False,
    )
    assert as_service.returncode == 0, as_service.stderr
    assert as_service.stdout == (state / "web-tokens.json").read_bytes()
    assert TokenStore(state).verify(token)
