"""The SSRF policy: every refused address class, IPv4 and IPv6 (IPv4 carried in IPv6 included), the allow-list,
the URL checks made when subscribing, and the check on the address a delivery actually connects to."""

from __future__ import annotations

import ipaddress
import re
import socket
from typing import Any

import httpcore2
import pytest

from service.webhooks.addresses import AddressRefusedError, GuardedBackend, check_url, refusal
from tests.support.receiver import Receiver, parse_networks

REFUSED = {
    "127.0.0.1": "loopback",
    "127.8.9.10": "loopback",
    "::1": "loopback",
    "10.1.2.3": "private",
    "172.16.0.1": "private",
    "192.168.1.1": "private",
    "fc00::1": "private",
    "fd12:3456::1": "private",
    "169.254.169.254": "link-local",
    "fe80::1": "link-local",
    "224.0.0.1": "multicast",
    "239.255.255.250": "multicast",
    "ff02::1": "multicast",
    "0.0.0.0": "unspecified",
    "::": "unspecified",
    "240.0.0.1": "reserved",
    "255.255.255.255": "reserved",
    "100.64.0.1": "not globally routable",  # carrier-grade NAT
    "192.0.2.10": "private",  # documentation
    "2001:db8::1": "private",  # documentation
    # IPv4 inside IPv6 is judged by the IPv4 address.
    "::ffff:127.0.0.1": "loopback",
    "::ffff:10.0.0.1": "private",
    "::ffff:169.254.169.254": "link-local",
    "::127.0.0.1": "loopback",  # IPv4-compatible
    "2002:7f00:1::1": "loopback",  # 6to4 of 127.0.0.1
    "64:ff9b::a9fe:a9fe": "link-local",  # NAT64 of 169.254.169.254
}
PUBLIC = ["8.8.8.8", "1.1.1.1", "93.184.216.34", "2606:4700:4700::1111", "::ffff:8.8.8.8", "2002:808:808::1"]


@pytest.mark.parametrize(("address", "kind"), REFUSED.items())
def test_refused_address_classes(address: str, kind: str) -> None:
    reason = refusal(ipaddress.ip_address(address))
    assert reason is not None and kind in reason, reason


@pytest.mark.parametrize("address", PUBLIC)
def test_public_addresses_pass(address: str) -> None:
    assert refusal(ipaddress.ip_address(address)) is None


def test_the_allow_list_opens_only_its_ranges() -> None:
    allowed = parse_networks(["127.0.0.0/8", "10.20.0.0/16", "::1"])
    assert refusal(ipaddress.ip_address("127.0.0.1"), allowed) is None
    assert refusal(ipaddress.ip_address("::ffff:127.0.0.1"), allowed) is None  # the mapped form too
    assert refusal(ipaddress.ip_address("::1"), allowed) is None
    assert refusal(ipaddress.ip_address("10.20.3.4"), allowed) is None
    assert refusal(ipaddress.ip_address("10.21.0.1"), allowed) == "a private address"
    assert refusal(ipaddress.ip_address("169.254.169.254"), allowed) == "a link-local address"


@pytest.mark.parametrize(
    ("url", "fragment"),
    [
        ("ftp://example.com/hook", "scheme"),
        ("file:///etc/passwd", "scheme"),
        ("gopher://127.0.0.1:6379/_INFO", "scheme"),
        ("example.com/hook", "scheme"),
        ("http:///hook", "no host"),
        ("https://user:pass@example.com/hook", "credentials"),
        ("https://example.com/hook#frag", "fragment"),
        ("http://example.com:99999/hook", "malformed"),
        ("http://127.0.0.1/hook", "loopback"),
        ("http://localhost:8000/hook", "loopback"),
        ("http://[::1]/hook", "loopback"),
        ("http://[::ffff:127.0.0.1]/hook", "loopback"),
        ("http://2130706433/hook", "loopback"),  # 127.0.0.1 as a decimal number
        ("http://0x7f.1/hook", "loopback"),
        ("http://10.0.0.1/hook", "private"),
        ("http://169.254.169.254/latest/meta-data/", "link-local"),
        ("http://[fe80::1]/hook", "link-local"),
        ("http://224.0.0.1/hook", "multicast"),
        ("http://0.0.0.0:8000/hook", "unspecified"),
        ("http://240.0.0.1/hook", "reserved"),
        ("http://does-not-exist.invalid/hook", "does not resolve"),
    ],
)
def test_check_url_refuses(url: str, fragment: str) -> None:
    with pytest.raises(AddressRefusedError, match=fragment):
        check_url(url)


def test_check_url_allows_what_the_setting_opens() -> None:
    assert check_url("http://127.0.0.1:9/hook", parse_networks(["127.0.0.0/8"])) == [ipaddress.ip_address("127.0.0.1")]
    assert check_url("https://93.184.216.34/hook") == [ipaddress.ip_address("93.184.216.34")]


def _resolver(*addresses: str) -> Any:
    """A DNS answer of our choosing, in getaddrinfo's shape (the policy's resolver seam)."""

    def resolve(host: str, port: int) -> list[tuple[Any, ...]]:
        return [
            (socket.AF_INET6 if ":" in a else socket.AF_INET, socket.SOCK_STREAM, 6, "", (a, port)) for a in addresses
        ]

    return resolve


def test_a_host_with_any_refused_address_is_refused_when_subscribing() -> None:
    with pytest.raises(AddressRefusedError, match=re.escape("10.0.0.5, a private address")):
        check_url("https://hooks.example.com/x", resolver=_resolver("93.184.216.34", "10.0.0.5"))


def test_dns_rebinding_is_caught_on_the_connection() -> None:
    """The host resolved to a public address when the subscription was made; at delivery time it resolves to
    loopback, where a real server listens. The backend never connects to it."""
    receiver = Receiver().start()
    try:
        answers = iter([["93.184.216.34"], ["127.0.0.1"]])

        def rebinding(host: str, port: int) -> list[tuple[Any, ...]]:
            return _resolver(*next(answers))(host, port)

        check_url(f"http://rebind.example:{receiver.port}/hook", resolver=rebinding)
        backend = GuardedBackend(resolver=rebinding)
        with pytest.raises(AddressRefusedError, match=re.escape("127.0.0.1 (a loopback address)")):
            backend.connect_tcp("rebind.example", receiver.port, timeout=2)
        assert backend.peer is None
        assert receiver.received() == []
    finally:
        receiver.stop()


def test_the_backend_connects_only_to_allowed_addresses_and_records_the_peer() -> None:
    receiver = Receiver().start()
    try:
        # One refused and one allowed answer: only the allowed one is connected to.
        backend = GuardedBackend(parse_networks(["127.0.0.1/32"]), resolver=_resolver("10.0.0.9", "127.0.0.1"))
        stream = backend.connect_tcp("mixed.example", receiver.port, timeout=2)
        stream.close()
        assert backend.peer == f"127.0.0.1:{receiver.port}"
        refused_port = receiver.port
    finally:
        receiver.stop()
    with pytest.raises(httpcore2.ConnectError):
        GuardedBackend(parse_networks(["127.0.0.1/32"])).connect_tcp("127.0.0.1", refused_port, timeout=2)
