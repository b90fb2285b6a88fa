"""The `hostd` command: `hostd serve` runs the daemon, every other subcommand is a client.

Clients find the daemon at `--socket PATH`, else `$HOSTD_SOCKET`, else
/run/hostd/hostd.sock, and talk JSON-RPC to it (../shared/spec/api.md).

Exit status, the same for every client subcommand:

- 0: done (for `run`: the job completed; for `watch`: stopped with Ctrl-C)
- 1: the daemon refused or failed the request (its message and code on
  stderr), or the job `run` followed did not complete
- 2: usage: bad arguments, or a local file that cannot be read
- 3: the daemon cannot be reached, or it closed the connection
- 130: interrupted (Ctrl-C outside a question, or `run` stopped following)
"""

from __future__ import annotations

import argparse
import asyncio
import importlib
import math
import os
import sys
from collections.abc import Awaitable, Callable, Sequence
from typing import TYPE_CHECKING, Any

from hostd import __version__

if TYPE_CHECKING:  # the client modules (and rich) load only when a client command runs
    from hostd.cli.client import Client
    from hostd.cli.render import Output

EXIT_OK = 0
EXIT_API = 1
EXIT_USAGE = 2
EXIT_UNREACHABLE = 3
EXIT_INTERRUPTED = 130

Command = Callable[["Client", argparse.Namespace, "Output"], Awaitable[int]]


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    try:
        # `serve`'s own options belong to hostd.service (imported only for it): they
        # come back unparsed, and are an error for every other command.
        args, rest = parser.parse_known_args(argv)
        if rest and args.command != "serve":
            getattr(args, "parser", parser).error(f"unrecognized arguments: {' '.join(rest)}")
        if args.command is None:
            parser.print_help(sys.stderr)
            return EXIT_USAGE
        if args.command == "serve":
            return _serve(args, rest)
        handler: Callable[[argparse.Namespace], int] = args.handler
        return handler(args)
    except SystemExit as exc:  # --help, --version, usage errors: argparse's own status
        if exc.code is None:
            return EXIT_OK
        return exc.code if isinstance(exc.code, int) else EXIT_USAGE


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="hostd", description="Host daemon for g2core and grbl CNC and laser controllers."
    )
    parser.add_argument("--version", action="version", version=f"hostd {__version__}")
    _client_options(parser, default=None)
    parser.set_defaults(command=None)
    # The same options after the subcommand; SUPPRESS keeps one given before it.
    common = argparse.ArgumentParser(add_help=False)
    _client_options(common, default=argparse.SUPPRESS)
    sub = parser.add_subparsers(title="commands", metavar="COMMAND")

    serve = sub.add_parser(
        "serve",
        add_help=False,  # `hostd serve --help` is hostd.service's help
        help="run the daemon in the foreground (hostd serve --help for its options)",
    )
    serve.set_defaults(command="serve")

    def client(name: str, command: str, help: str) -> argparse.ArgumentParser:
        p = sub.add_parser(name, parents=[common], help=help, description=help)
        p.set_defaults(command=name, handler=_client_handler(command), parser=p)
        return p

    p = client("status", "status", "all machines, or one machine's snapshot")
    p.add_argument("machine", nargs="?", metavar="MACHINE")

    p = client("send", "send", "send lines to a machine, one at a time, and print its answers")
    p.add_argument("machine", metavar="MACHINE")
    p.add_argument("lines", nargs="+", metavar="LINE")
    p.add_argument("--timeout", type=_positive, help="seconds to wait for each answer")

    p = client("run", "run", "upload a G-code file, run it, follow it to its end")
    p.add_argument("file", metavar="FILE")
    p.add_argument("--machine", "-m", required=True, metavar="M")
    p.add_argument("--start-line", type=_at_least_one, metavar="N", help="first file line to run")
    p.add_argument("--name", help="file name in the daemon's jobs directory (default: FILE's)")
    p.add_argument(
        "--from",
        dest="from_line",
        type=_at_least_one,
        metavar="LINE",
        help="resume at LINE: show the restore and approach plan, ask, then run (job.recovery)",
    )
    p.add_argument("--yes", "-y", action="store_true", help="do not ask before a --from resume")
    p.add_argument(
        "--force",
        action="store_true",
        help="start a file job.start refuses (beyond the travel, lines the board would refuse)",
    )

    p = client("analyze", "analyze", "a G-code file's figures: bounds, estimate, warnings")
    p.add_argument("file", metavar="FILE")
    p.add_argument("--machine", "-m", metavar="M", help="with this machine's speeds and travel")
    p.add_argument("--name", help="file name in the daemon's jobs directory (default: FILE's)")

    for name, help in (
        ("hold", "feedhold (!)"),
        ("resume", "cycle start (~)"),
        ("clear", "clear an alarm or shutdown"),
        ("reset", "reset the controller (0x18) and re-synchronise"),
    ):
        client(name, "action", help).add_argument("machine", metavar="MACHINE")
    client("cancel", "cancel", "cancel the running job").add_argument("machine", metavar="MACHINE")
    client(
        "tool-change-done", "tool_change_done", "the tool is changed: the waiting job goes on"
    ).add_argument("machine", metavar="MACHINE")

    p = client("home", "home", "home the machine (all axes, or AXES like xyz)")
    p.add_argument("machine", metavar="MACHINE")
    p.add_argument("axes", nargs="?", metavar="AXES")

    p = client("zero", "zero", "set work zero on AXES (like xyz) at the current position")
    p.add_argument("machine", metavar="MACHINE")
    p.add_argument("axes", metavar="AXES")

    p = client("probe", "probe", "probe work zero with the touch plate: Z, or an XYZ corner")
    p.add_argument("machine", metavar="MACHINE")
    p.add_argument("--xyz", action="store_true", help="the corner: Z, then X and Y")
    p.add_argument("--plate", type=_non_negative, metavar="MM", help="the plate's thickness")
    p.add_argument("--feed", type=_positive, metavar="F", help="probe feed, mm/min")
    p.add_argument("--max-travel", type=_positive, metavar="MM", help="the farthest it probes")
    p.add_argument("--retract", type=_non_negative, metavar="MM", help="lift after each touch")
    p.add_argument("--tool-diameter", type=_non_negative, metavar="MM", help="the bit (--xyz)")
    p.add_argument("--wait", type=_positive, default=30.0, metavar="S", help="for the touch")
    p.add_argument(
        "--confirmed",
        action="store_true",
        help="you saw the probe work (only where the board cannot show its input)",
    )

    p = client("override", "override", "set feed, spindle and rapid overrides (percent)")
    p.add_argument("machine", metavar="MACHINE")
    for name in ("feed", "spindle", "rapid"):
        p.add_argument(f"--{name}", type=_at_least_one, metavar="N", help=f"{name} percent")

    p = client("spindle", "spindle", "turn the spindle on (clockwise, or --ccw) or off")
    p.add_argument("machine", metavar="MACHINE")
    p.add_argument("state", choices=("on", "off"))
    p.add_argument("--speed", type=_non_negative, metavar="S", help="spindle speed (S word)")
    p.add_argument("--ccw", action="store_true", help="counter-clockwise (M4)")

    p = client("frame", "frame", "trace a G-code file's bounding box (beam off, or --power)")
    p.add_argument("machine", metavar="MACHINE")
    p.add_argument("file", metavar="FILE")
    p.add_argument("--power", type=_non_negative, default=0.0, metavar="P", help="laser percent")
    p.add_argument("--feed", type=_positive, metavar="F", help="mm/min (default 1000)")
    p.add_argument("--name", help="file name in the daemon's jobs directory (default: FILE's)")

    p = client("laser-test", "laser_test", "fire the laser standing still, then off")
    p.add_argument("machine", metavar="MACHINE")
    p.add_argument("power", type=_positive, metavar="PERCENT")
    p.add_argument("--seconds", type=_positive, default=0.5, metavar="S", help="at most 2")

    p = client("macro", "macro", "list the config's macros, or run one (NAME key=value ...)")
    p.add_argument("action", choices=("list", "run"))
    p.add_argument("machine", nargs="?", metavar="MACHINE")
    p.add_argument("name", nargs="?", metavar="NAME")
    p.add_argument("params", nargs="*", metavar="KEY=VALUE")

    p = client("jobs", "jobs", "recent jobs, newest first (of MACHINE, or every machine's)")
    # MACHINE as the other commands take it; --machine as it always was.
    p.add_argument("machine_arg", nargs="?", metavar="MACHINE")
    p.add_argument("--machine", "-m", metavar="M")
    p.add_argument("--limit", type=_at_least_one, default=50, metavar="N")

    p = client("faults", "faults", "a machine's active faults; one cleared or overridden first")
    p.add_argument("machine", metavar="MACHINE")
    p.add_argument("--all", action="store_true", help="every fault of the table, active or not")
    way = p.add_mutually_exclusive_group()
    way.add_argument("--clear", metavar="FAULT", help="clear it (serial, lexical, underflow)")
    way.add_argument(
        "--override", metavar="FAULT", help="run as if it were not active (lid, coolant)"
    )
    way.add_argument("--remove-override", metavar="FAULT", help="take its override back")

    p = client("watch", "watch", "status, exceptions and supervisor changes live, until Ctrl-C")
    p.add_argument("machine", nargs="?", metavar="MACHINE")

    token = sub.add_parser("token", help="the web dashboard's access tokens (docs/web.md)")
    token.set_defaults(command="token", handler=_token_usage(token))
    tokens = token.add_subparsers(title="token commands", metavar="ACTION")
    for action, help in (
        ("create", "make a token; it is printed once, only its hash is kept"),
        ("list", "the tokens on file, by id"),
        ("revoke", "remove a token by its id"),
    ):
        p = tokens.add_parser(action, help=help, description=help)
        p.set_defaults(command="token", handler=_token_handler(action))
        p.add_argument("--config", required=True, help="the daemon's TOML config (its state_dir)")
        if action == "create":
            p.add_argument("--name", default="", help="a note saying whose token it is")
        if action == "revoke":
            p.add_argument("id", metavar="ID")
    return parser


def _token_usage(parser: argparse.ArgumentParser) -> Callable[[argparse.Namespace], int]:
    def usage(args: argparse.Namespace) -> int:
        parser.print_help(sys.stderr)
        return EXIT_USAGE

    return usage


def _token_handler(action: str) -> Callable[[argparse.Namespace], int]:
    """`hostd token ...`: local, on the daemon's state_dir (the daemon need not run)."""

    def handler(args: argparse.Namespace) -> int:
        from hostd.api.tokens import TokenStore
        from hostd.config import ConfigError, load_config

        try:
            store = TokenStore(load_config(args.config).daemon.state_dir)
            if action == "create":
                print(store.create(args.name))
            elif action == "list":
                for record in store.records():
                    print(f"{record.id}  {record.name}")
            elif not store.revoke(args.id):
                print(f"hostd: no token {args.id!r}", file=sys.stderr)
                return EXIT_API
        except ConfigError as exc:
            print(f"hostd: {exc}", file=sys.stderr)
            return EXIT_USAGE
        except OSError as exc:
            print(f"hostd: {exc}", file=sys.stderr)
            return EXIT_API
        return EXIT_OK

    return handler


def _client_options(parser: argparse.ArgumentParser, default: Any) -> None:
    parser.add_argument(
        "--socket",
        default=default,
        metavar="PATH",
        help="the daemon's socket (default: $HOSTD_SOCKET, else /run/hostd/hostd.sock)",
    )
    parser.add_argument(
        "--json", action="store_true", default=default, help="print results as JSON"
    )


def _positive(text: str) -> float:
    value = float(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"{text}: must be > 0")
    return value


def _non_negative(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not math.isfinite(value) or value < 0:
        raise argparse.ArgumentTypeError(f"must be zero or more: {text!r}")
    return value


def _at_least_one(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text}: must be >= 1")
    return value


def socket_path(arg: str | None) -> str:
    from hostd.cli.client import DEFAULT_SOCKET, SOCKET_ENV

    return arg or os.environ.get(SOCKET_ENV) or DEFAULT_SOCKET


def _serve(args: argparse.Namespace, rest: list[str]) -> int:
    """`hostd serve`: the daemon lives in hostd.service, imported only when asked for,
    so that client commands start without loading the daemon's stack."""
    try:
        service = importlib.import_module("hostd.service")
    except ModuleNotFoundError as exc:
        if exc.name != "hostd.service":
            raise
        print("hostd: serve is not available in this build", file=sys.stderr)
        return EXIT_USAGE
    parser = argparse.ArgumentParser(prog="hostd serve", description="Run the daemon.")
    service.add_arguments(parser)
    serve_args = parser.parse_args(rest)
    if getattr(serve_args, "socket", None) is None and args.socket is not None:
        serve_args.socket = args.socket  # `hostd --socket PATH serve ...`
    status: int = service.serve_main(serve_args)
    return status


def _client_handler(name: str) -> Callable[[argparse.Namespace], int]:
    def handler(args: argparse.Namespace) -> int:
        from hostd.cli import commands

        command: Command = getattr(commands, name)
        return run_client(args, command)

    return handler


def run_client(args: argparse.Namespace, command: Command) -> int:
    """Connect, run one command, and turn every way it can fail into a message and a status."""
    from hostd.cli.client import Client, ClientError, RpcError
    from hostd.cli.commands import CliError
    from hostd.cli.render import json_line, make_output

    out = make_output(json_output=bool(args.json))
    path = socket_path(args.socket)

    async def session() -> int:
        async with Client(path) as c:
            return await command(c, args, out)

    try:
        return asyncio.run(session())
    except RpcError as exc:
        out.message(f"hostd: error {exc.code}: {exc.message}")
        for note in getattr(exc, "__notes__", ()):
            out.message(f"hostd: {note}")
        if exc.data is not None and exc.code not in (-32602, 1005):
            out.message(f"hostd: details: {json_line(exc.data)}")
        return EXIT_API
    except CliError as exc:
        out.message(f"hostd: {exc.message}")
        return exc.status
    except ClientError as exc:
        out.message(f"hostd: {exc}")
        return EXIT_UNREACHABLE
    except KeyboardInterrupt:
        out.message("hostd: interrupted")
        return EXIT_INTERRUPTED


if __name__ == "__main__":
    sys.exit(main())
