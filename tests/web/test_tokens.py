"""Tokens on disk, the `[web]` table, and `hostd token`."""

from __future__ import annotations

import stat
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
    assert stat.S_IMODE(store.path.stat().st_mode) == 0o600
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
