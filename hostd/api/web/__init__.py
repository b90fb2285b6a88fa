"""The dashboard's HTTP server (`[web]`, docs/web.md): the page, its WebSocket, uploads.

aiohttp serves it: one maintained asyncio library with HTTP, WebSockets and
streamed request bodies, so nothing here parses HTTP or frames WebSockets.

One API. The WebSocket at `/api` carries the same JSON-RPC 2.0 as the Unix
socket, one message a WebSocket text frame, answered by the same method
table through `rpc.answer`. Its peer is a `WebClient`, a `client.Client`
with the WebSocket for a stream, so subscriptions, the bounded outbound
queue (full: the client is dropped) and the disconnect hooks are the Unix
socket's own. `POST /files/<name>` streams a request body into the jobs
directory through the same staging, name rules and quota as `file.upload`.

A module a concept:

- `app.py`: `WebServer`, the routes, the page and its assets, start and close;
- `auth.py`: who may come in: the Host check, tokens and sessions (login,
  logout, revocation), the login rate limit, the Origin check, watch only;
- `addresses.py`: who the client is behind a trusted proxy, and its scheme;
- `connections.py`: the connection caps and the header timeout, applied
  before aiohttp reads a byte;
- `files.py`: `/files/<name>`, a program up (streamed) and down (the preview);
- `websocket.py`: the `/api` WebSocket and its `WebClient`;
- `responses.py`: the headers every response carries, and the error body.

Security (a browser is not a Unix socket):

- Every request but the login page and its two assets needs a token
  (`hostd token create`, tokens.py): `Authorization: Bearer <token>`, or the
  `hostd_session` cookie that `POST /login` sets (HttpOnly, SameSite=Strict),
  which holds a server-side session id, never the token.
- Revoking a token ends its sessions and closes its WebSockets: the token
  file is looked at every REVOKE_POLL seconds.
- `POST /login` is rate-limited per client address (`login_attempts` a minute);
  the client address is the peer's, or what a `trusted_proxies` proxy says.
- Connections are capped in all and per client address, and a connection
  must send its request's headers within `header_timeout`; an idle one is
  closed after `idle_timeout`. So the web server can never take the
  descriptors the Unix socket, the serial ports and SQLite need.
- The WebSocket handshake, the login and uploads refuse an `Origin` other
  than the served host itself (cross-site WebSocket hijacking, login CSRF).
- Every response carries a Content-Security-Policy that allows scripts,
  styles, images and connections from this origin only: no inline script,
  nothing from the internet, no framing.
- `[web] control = false`: only the methods that read are served; the rest
  answer -32601 naming the setting, and uploads are refused (403).
"""

from hostd.api.web.app import WebServer
from hostd.api.web.auth import COOKIE

__all__ = ["COOKIE", "WebServer"]
