"""Where webhooks may be sent: the SSRF policy on outbound URLs, checked when subscribing and on every connection.

A webhook URL is chosen by whoever can call the API, and the worker that posts to it sits inside the
deployment's network, next to Redis, the database and cloud metadata endpoints. So a URL must be http or https,
and every address its host resolves to must be globally routable: loopback, private, link-local (which includes
169.254.169.254, the cloud metadata service), multicast, reserved, unspecified and other special-purpose ranges
are refused, for IPv4 and IPv6 alike. IPv6 forms that carry an IPv4 address (IPv4-mapped `::ffff:a.b.c.d`,
IPv4-compatible `::a.b.c.d`, 6to4 `2002::/16` and the NAT64 prefix `64:ff9b::/96`) are judged by that IPv4
address. Operators open specific ranges with the `webhook_allowed_networks` setting (an internal receiver, or
loopback in tests).

The check is made twice: when a subscription is created or its URL changed (a clear 4xx), and again by the
delivery worker on the address it actually connects to (`GuardedBackend`), because a host's DNS answer may change
after the first check (DNS rebinding). Redirects are never followed, so a receiver cannot bounce a delivery to a
refused address either.
"""

from __future__ import annotations

import ipaddress
import socket
from collections.abc import Callable, Iterable, Sequence
from typing import Any
from urllib.parse import urlsplit

import httpcore2

IPAddress = ipaddress.IPv4Address | ipaddress.IPv6Address
IPNetwork = ipaddress.IPv4Network | ipaddress.IPv6Network
Resolver = Callable[[str, int], list[tuple[Any, ...]]]

SCHEMES = {"http": 80, "https": 443}
_NAT64 = ipaddress.IPv6Network("64:ff9b::/96")
_IPV4_COMPATIBLE = ipaddress.IPv6Network("::/96")


class AddressRefusedError(Exception):
    """A URL, or the address a delivery would connect to, is outside the policy; the message says why."""


def resolve(host: str, port: int) -> list[tuple[Any, ...]]:
    """getaddrinfo for TCP; the seam the policy resolves through."""
    return socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)


def embedded_ipv4(ip: IPAddress) -> IPAddress:
    """The IPv4 address an IPv6 address stands for, when it is one of the forms that carry one; else `ip`."""
    if isinstance(ip, ipaddress.IPv4Address):
        return ip
    if ip.ipv4_mapped is not None:
        return ip.ipv4_mapped
    if ip.sixtofour is not None:
        return ip.sixtofour
    if ip in _NAT64 or (ip in _IPV4_COMPATIBLE and int(ip) > 1):
        return ipaddress.IPv4Address(int(ip) & 0xFFFFFFFF)
    return ip


def refusal(ip: IPAddress, allowed: Sequence[IPNetwork] = ()) -> str | None:
    """Why the policy refuses `ip` (a few words: "a loopback address"), or None when it may be connected to.

    An IPv6 form that carries an IPv4 address is judged by that address; the allow-list may name either form.
    """
    target = embedded_ipv4(ip)
    if any(candidate in network for candidate in (ip, target) for network in allowed):
        return None
    if target.is_unspecified:
        return "an unspecified address"
    if target.is_loopback:
        return "a loopback address"
    if target.is_link_local:
        return "a link-local address"
    if target.is_multicast:
        return "a multicast address"
    if target.is_reserved:
        return "a reserved address"
    if target.is_private:
        return "a private address"
    if not target.is_global:
        return "a special-purpose address that is not globally routable"
    return None


def _host_port(url: str) -> tuple[str, int]:
    """The URL's host and port after the syntactic checks; AddressRefusedError says what is wrong."""
    try:
        parts = urlsplit(url)
        port = parts.port
    except ValueError as exc:
        raise AddressRefusedError(f"the URL is malformed ({exc})") from None
    scheme = parts.scheme.lower()
    if scheme not in SCHEMES:
        raise AddressRefusedError(f"the URL scheme must be http or https, not {parts.scheme or 'missing'!r}")
    if not parts.hostname:
        raise AddressRefusedError("the URL has no host")
    if parts.username is not None or parts.password is not None:
        raise AddressRefusedError(
            "the URL carries credentials (user:password@); receivers authenticate deliveries by their signature"
        )
    if parts.fragment:
        raise AddressRefusedError("the URL has a fragment (#...), which is never sent to a server")
    return parts.hostname, port if port is not None else SCHEMES[scheme]


def _ip(sockaddr: tuple[Any, ...]) -> IPAddress:
    # An IPv6 link-local answer may carry a zone ("fe80::1%eth0"); the address itself is what the policy judges.
    return ipaddress.ip_address(str(sockaddr[0]).split("%", 1)[0])


def check_url(url: str, allowed: Sequence[IPNetwork] = (), resolver: Resolver = resolve) -> list[IPAddress]:
    """Refuse a URL whose scheme is not http(s) or whose host resolves to any refused address.

    Any, not all: a host with one public and one private address is refused, since which one a connection ends
    up at is the DNS server's choice. Returns the addresses the host resolved to.
    """
    host, port = _host_port(url)
    try:
        infos = resolver(host, port)
    except (socket.gaierror, UnicodeError) as exc:
        raise AddressRefusedError(f"the host {host!r} does not resolve ({exc})") from None
    addresses = list(dict.fromkeys(_ip(info[4]) for info in infos))
    if not addresses:
        raise AddressRefusedError(f"the host {host!r} does not resolve")
    for ip in addresses:
        reason = refusal(ip, allowed)
        if reason is not None:
            raise AddressRefusedError(
                f"the host {host!r} resolves to {ip}, {reason}; webhooks are only sent to public addresses "
                "unless the setting webhook_allowed_networks opens a range"
            )
    return addresses


class GuardedBackend(httpcore2.SyncBackend):
    """httpcore's network backend with the policy applied to every TCP connection it opens.

    The host is resolved here and only allowed addresses are connected to (the socket is opened to the checked
    IP itself, so nothing can resolve differently in between); TLS still verifies the certificate against the
    URL's host name, which httpcore passes to the TLS layer separately. `peer` records the address connected to.
    """

    def __init__(self, allowed: Sequence[IPNetwork] = (), resolver: Resolver = resolve) -> None:
        self.allowed = tuple(allowed)
        self.resolver = resolver
        self.peer: str | None = None

    def connect_tcp(
        self,
        host: str,
        port: int,
        timeout: float | None = None,
        local_address: str | None = None,
        socket_options: Iterable[Any] | None = None,
    ) -> httpcore2.NetworkStream:
        try:
            infos = self.resolver(host, port)
        except (socket.gaierror, UnicodeError) as exc:
            raise httpcore2.ConnectError(f"{host} does not resolve ({exc})") from exc
        refused: list[str] = []
        last_error: Exception | None = None
        for ip in dict.fromkeys(_ip(info[4]) for info in infos):
            reason = refusal(ip, self.allowed)
            if reason is not None:
                refused.append(f"{ip} ({reason})")
                continue
            try:
                stream = super().connect_tcp(str(ip), port, timeout, local_address, socket_options)
            except (httpcore2.ConnectError, httpcore2.ConnectTimeout) as exc:
                last_error = exc
                continue
            self.peer = f"[{ip}]:{port}" if ip.version == 6 else f"{ip}:{port}"
            return stream
        if last_error is not None:
            raise last_error
        raise AddressRefusedError(
            f"{host} resolves only to refused addresses: {', '.join(refused) or 'none'} "
            "(setting webhook_allowed_networks)"
        )
