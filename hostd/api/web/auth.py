"""Who may use the web server, and for what.

- The Host a request names must be ours (DNS rebinding), before anything else.
- Every request but the login page and its two assets needs a token
  (`hostd token create`, tokens.py): `Authorization: Bearer <token>`, or the
  `hostd_session` cookie that `POST /login` sets (HttpOnly, SameSite=Strict),
  which holds a server-side session id, never the token.
- The token file is looked at every REVOKE_POLL seconds: a revoked token's
  sessions end and its WebSockets close.
- `POST /login` is rate-limited per client address (`login_attempts` a minute).
- The WebSocket handshake, the login and uploads refuse an `Origin` other
  than the served host itself (cross-site WebSocket hijacking, login CSRF).
- `[web] control = false`: only the methods in WATCH_METHODS are served; the
  rest answer -32601 naming the setting.
"""

from __future__ import annotations

import asyncio
import ipaddress
import time
from collections.abc import Awaitable, Callable, Mapping
from typing import Any, Final, NoReturn

import structlog
from aiohttp import web

from hostd.api import rpc
from hostd.api.tally import Tally
from hostd.api.tokens import Sessions, TokenStore
from hostd.api.web import addresses
from hostd.api.web.addresses import IPNetwork
from hostd.api.web.responses import error
from hostd.api.webconfig import WebConfig

log = structlog.get_logger(__name__)

COOKIE: Final = "hostd_session"
LOGIN_WINDOW: Final = 60.0
# How often the token file is looked at for revocations (a stat; read only when it changed).
REVOKE_POLL: Final = 0.25
# What a watch-only dashboard may call: reads, and its own subscriptions.
WATCH_METHODS: Final = frozenset(
    {
        "rpc.discover",
        "daemon.info",
        "machine.list",
        "machine.status",
        "settings.get",
        "file.list",
        "file.analyze",
        "job.get",
        "job.list",
        "fault.list",
        "macro.list",
        "subscribe",
        "unsubscribe",
    }
)
PUBLIC: Final = frozenset({"/login", "/static/login.js", "/static/style.css", "/static/icon.svg"})
TOKEN_ID: Final = web.RequestKey("token_id", str)  # the token a request came in with


def watch_only(methods: Mapping[str, rpc.Method]) -> dict[str, rpc.Method]:
    """The table with every method outside WATCH_METHODS answering -32601."""
    return {
        name: method if name in WATCH_METHODS else rpc.Method(_refusal(name), method.params_model)
        for name, method in methods.items()
    }


def _refusal(name: str) -> Callable[..., Awaitable[NoReturn]]:
    async def refused(*_: Any) -> NoReturn:
        message = f"{name} is not available: the web API is watch only ([web] control = false)"
        raise rpc.RpcError(rpc.METHOD_NOT_FOUND, message)

    return refused


class LoginLimiter:
    """At most `attempts` logins per address per LOGIN_WINDOW seconds, successful or not."""

    def __init__(self, attempts: int, clock: Callable[[], float] = time.monotonic) -> None:
        self._attempts = attempts
        self._clock = clock
        self._seen: dict[str, list[float]] = {}

    def allow(self, address: str) -> float | None:
        """None when this attempt may go on; else the seconds until one may."""
        now = self._clock()
        recent = [t for t in self._seen.get(address, []) if now - t < LOGIN_WINDOW]
        if len(recent) >= self._attempts:
            self._seen[address] = recent
            return LOGIN_WINDOW - (now - recent[0])
        recent.append(now)
        self._seen[address] = recent
        # Forget quiet addresses, so the table cannot grow without bound.
        if len(self._seen) > 10_000:
            self._seen = {a: ts for a, ts in self._seen.items() if now - ts[-1] < LOGIN_WINDOW}
        return None


class Auth:
    """The server's tokens, sessions and login limit, and the checks made of each request."""

    def __init__(
        self, tokens: TokenStore, config: WebConfig, clock: Callable[[], float] = time.monotonic
    ) -> None:
        self._tokens = tokens
        self._sessions = Sessions(config.session_expiry, clock)
        self._config = config
        self.trusted: list[IPNetwork] = list(config.trusted_proxies)
        self._limiter = LoginLimiter(config.login_attempts, clock)
        self._hosts = {"localhost", config.host.strip("[]").lower(), *map(str.lower, config.hosts)}
        # What a peer on the network can repeat at will: a record a second at most, counted.
        self._unknown_host = Tally(log, "web request for an unknown host refused", clock=clock)
        self._rate_limited = Tally(log, "web login rate-limited", clock=clock)
        self._bad_login = Tally(log, "web login refused", clock=clock)

    def flush_logs(self) -> None:
        """Log the refusals still tallied (the server is closing)."""
        for tally in (self._unknown_host, self._rate_limited, self._bad_login):
            tally.flush()

    async def watch_tokens(self, revoked: Callable[[set[str]], object]) -> None:
        """Every REVOKE_POLL, the ids of the tokens on file, for `revoked` to end the others'
        sessions and close their WebSockets."""
        while True:
            await asyncio.sleep(REVOKE_POLL)
            try:
                ids = await asyncio.to_thread(self._tokens.ids)
            except (OSError, ValueError, TypeError, KeyError) as exc:
                log.error("web token file unreadable; sessions kept", error=str(exc))
                continue
            revoked(ids)

    def keep_only(self, ids: set[str]) -> int:
        """End the sessions of every token not in `ids`; how many ended."""
        return self._sessions.keep_only(ids)

    def client_address(self, request: web.Request) -> str:
        """The client, behind any trusted proxy (addresses.py)."""
        return addresses.client_address(request, self.trusted)

    def scheme(self, request: web.Request) -> str:
        """The scheme the browser used, as a trusted proxy says (addresses.py)."""
        return addresses.scheme(request, self.trusted)

    def _known_host(self, host: str) -> bool:
        """The Host a request names is ours: an address, localhost, `listen`'s, or a [web] host.

        A page on a name the attacker controls, made to resolve to this machine
        (DNS rebinding), names that name: it is refused before anything else.
        """
        name = host.rsplit(":", 1)[0] if not host.endswith("]") else host
        name = name.strip("[]").lower()
        if name in self._hosts:
            return True
        try:
            ipaddress.ip_address(name)
        except ValueError:
            return False
        return True

    def _token_id(self, request: web.Request) -> str | None:
        """The id of the token this request comes with (a bearer token or a session)."""
        header = request.headers.get("Authorization", "")
        scheme, _, value = header.partition(" ")
        if scheme.lower() == "bearer" and value.strip():
            return self._tokens.identify(value.strip())
        token_id = self._sessions.token_id(request.cookies.get(COOKIE))
        if token_id is None or token_id not in self._tokens.ids():
            return None  # revoked since: not even until the next poll
        return token_id

    @web.middleware
    async def authenticate(
        self, request: web.Request, handler: Callable[[web.Request], Awaitable[web.StreamResponse]]
    ) -> web.StreamResponse:
        if not self._known_host(request.host):
            self._unknown_host.warning(host=request.host)
            return error(421, f"this dashboard does not answer to {request.host!r} ([web] hosts)")
        if request.path in PUBLIC:
            return await handler(request)
        token_id = self._token_id(request)
        if token_id is not None:
            request[TOKEN_ID] = token_id
            return await handler(request)
        if request.method == "GET" and request.path == "/":
            raise web.HTTPFound("/login")
        return error(401, "a token is required: hostd token create (docs/web.md)")

    def foreign_origin(self, request: web.Request) -> bool:
        """An Origin header naming another site than the one serving this request."""
        origin = request.headers.get("Origin")
        if origin is None:
            return False  # not a browser: browsers send Origin on WebSockets and POSTs
        return origin != f"{self.scheme(request)}://{request.host}"

    async def login(self, request: web.Request) -> web.StreamResponse:
        if self.foreign_origin(request):
            return error(403, "login from another site refused")
        address = self.client_address(request)
        wait = self._limiter.allow(address)
        if wait is not None:
            self._rate_limited.warning(address=address)
            response = error(429, "too many login attempts; try again later")
            response.headers["Retry-After"] = str(max(1, round(wait)))
            return response
        try:
            body = await request.json()
            token = body["token"] if isinstance(body, dict) else None
        except (ValueError, KeyError):
            token = None
        token_id = self._tokens.identify(token) if isinstance(token, str) else None
        if token_id is None:
            self._bad_login.warning(address=address)
            return error(401, "not a valid token")
        log.info("web login", address=address, token=token_id)
        response = web.json_response({"control": self._config.control})
        session = self._sessions.create(token_id)
        secure = self.scheme(request) == "https"
        response.set_cookie(
            COOKIE, session, httponly=True, samesite="Strict", path="/", secure=secure
        )
        return response

    async def logout(self, request: web.Request) -> web.StreamResponse:
        self._sessions.end(request.cookies.get(COOKIE))
        response = web.json_response({})
        response.del_cookie(COOKIE, path="/")
        return response
