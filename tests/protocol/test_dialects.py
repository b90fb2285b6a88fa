"""The dialect registry (hostd/protocol/dialects.py): what each entry gives, by plain calls."""

from __future__ import annotations

import pickle
from collections.abc import Iterator
from dataclasses import replace

import pytest

from hostd.machine.config import MachineConfig
from hostd.protocol import dialects
from hostd.protocol.commands import InvalidCommand
from hostd.protocol.dialects import UnknownDialect
from hostd.protocol.g2core import G2Session
from hostd.protocol.grbl.session import GrblSession
from hostd.protocol.jobcheck import check_program
from hostd.protocol.states import MachineState

BUILTINS = {"g2core": G2Session, "grbl": GrblSession}


def test_the_built_in_dialects_are_registered_on_first_use() -> None:
    assert {"g2core", "grbl"} <= set(dialects.names())
    assert dialects.lookup(dialects.DEFAULT).name == "g2core"


@pytest.mark.parametrize("name", sorted(BUILTINS))
def test_an_entrys_session_is_its_dialects_and_speaks_its_words(name: str) -> None:
    spec = dialects.lookup(name)
    config = MachineConfig(id="m", data_port="/dev/null", dialect=name)
    session = spec.session(config)
    assert type(session) is BUILTINS[name]
    for code, text in spec.words.statuses.items():
        assert session.status_text(code) == text
    assert set(spec.words.states.values()) <= set(MachineState)
    assert spec.words.states  # every report the board prints maps onto a shared state


def test_the_dialects_own_config_keys_reach_its_session() -> None:
    g2 = MachineConfig(id="m", data_port="/dev/null", window=7, control_port="/dev/c")
    session = dialects.lookup("g2core").session(g2)
    assert isinstance(session, G2Session) and session.sender.window == 7 and session.dual
    grbl = MachineConfig(
        id="m", data_port="/dev/null", dialect="grbl", link_silence=3, startup_motion=True
    )
    session = grbl.spec.session(grbl)
    assert isinstance(session, GrblSession)
    assert (session.link_silence, session.startup_motion) == (3.0, True)
    assert pickle.loads(pickle.dumps(grbl)) == grbl  # its class is found by name


def test_a_name_no_dialect_registered_is_refused_naming_those_there_are() -> None:
    with pytest.raises(UnknownDialect, match="unknown dialect 'marlin': one of g2core, grbl"):
        dialects.lookup("marlin")


@pytest.fixture
def other_g2core() -> Iterator[dialects.DialectSpec]:
    spec = replace(dialects.lookup("g2core"), name="g2core-copy")
    dialects.register(spec)
    yield spec
    dialects.unregister(spec.name)


def test_a_taken_name_is_not_replaced_silently(other_g2core: dialects.DialectSpec) -> None:
    assert dialects.register(other_g2core) is other_g2core  # the same object: a no-op
    with pytest.raises(ValueError, match="already registered"):
        dialects.register(replace(other_g2core, ports=1))
    with pytest.raises(ValueError, match="already registered"):
        dialects.register(replace(dialects.lookup("grbl"), name="g2core"))
    assert dialects.lookup("g2core").ports == 2


@pytest.mark.parametrize("name", sorted(BUILTINS))
def test_an_entry_travels_to_an_analysis_worker_whole(name: str) -> None:
    """The job check runs on worker processes: the entry is pickled, not looked up there."""
    spec = dialects.lookup(name)
    again = pickle.loads(pickle.dumps(spec))
    assert again == spec and again.session is spec.session


def test_the_job_check_reads_the_entrys_encoder_and_table() -> None:
    lines = [(1, "G1 X1"), (2, "G28.2 X0"), (3, "$RST=$"), (4, "G1 X1 ?")]
    grbl = check_program(lines, dialect=dialects.lookup("grbl"), max_line_bytes=127)
    assert [(f.line, f.kind) for f in grbl.found] == [
        (2, "unsupported"),
        (3, "maintenance"),
        (4, "unsendable"),
    ]
    g2 = check_program(lines, dialect="g2core", max_line_bytes=512)
    # g2core homes with G28.2 and reads a `?` inside G-code as text; `$RST=` is no
    # command of its own, which its text mode would misread.
    assert [(f.line, f.kind) for f in g2.found] == [(3, "unsendable")]


def test_an_entrys_encoder_keeps_its_boards_line_limit() -> None:
    encode = dialects.lookup("grbl").encode_line
    assert encode("G1 X1", 127) == b"G1 X1\n"
    with pytest.raises(InvalidCommand):
        encode("G1 X" + "1" * 200, 127)
