"""Who a web client is: the peer's address, or, behind a trusted proxy, what the proxy says.

Only `[web] trusted_proxies` are believed (X-Forwarded-For, X-Forwarded-Proto);
the client address is what the login limit, the connection caps and the
logs count by.
"""

from __future__ import annotations

import ipaddress

from aiohttp import web

IPNetwork = ipaddress.IPv4Network | ipaddress.IPv6Network


def in_networks(address: str, networks: list[IPNetwork]) -> bool:
    try:
        ip = ipaddress.ip_address(address)
    except ValueError:
        return False
    return any(ip in net for net in networks)


def client_address(request: web.Request, trusted: list[IPNetwork]) -> str:
    """Who the client is: the peer, or, when the peer is a trusted proxy, the last
    address in X-Forwarded-For that is not one (the proxies append, right to left)."""
    address = request.remote or "?"
    if not trusted or not in_networks(address, trusted):
        return address
    hops = [h.strip() for h in ",".join(request.headers.getall("X-Forwarded-For", [])).split(",")]
    for hop in reversed([h for h in hops if h]):
        try:
            ipaddress.ip_address(hop)
        except ValueError:
            break  # garbage from further out: believe nothing past it
        address = hop
        if not in_networks(hop, trusted):
            break
    return address


def scheme(request: web.Request, trusted: list[IPNetwork]) -> str:
    """http, or what a trusted proxy says the browser used (X-Forwarded-Proto)."""
    if trusted and in_networks(request.remote or "", trusted):
        said = request.headers.get("X-Forwarded-Proto", "").split(",")[-1].strip().lower()
        if said in ("http", "https"):
            return said
    return request.scheme
