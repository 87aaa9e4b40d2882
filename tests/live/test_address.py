"""``--live [HOST:]PORT`` parsing: loopback by default, one-line errors."""

from __future__ import annotations

import socket

import pytest
from hypothesis import given
from hypothesis import strategies as st

from dobhil.errors import ConfigError
from dobhil.live import DEFAULT_HOST, LiveAddress, LiveAddressError, parse_live_address
from dobhil.live.address import check_bindable, exposure_warning, is_loopback, shown


@pytest.mark.parametrize(
    ("text", "host", "port"),
    [
        ("8765", "127.0.0.1", 8765),
        ("0", "127.0.0.1", 0),
        ("127.0.0.1:9000", "127.0.0.1", 9000),
        ("localhost:65535", "localhost", 65535),
        ("0.0.0.0:8765", "0.0.0.0", 8765),
        ("[::1]:8765", "::1", 8765),
        (" 8765 ", "127.0.0.1", 8765),
    ],
)
def test_valid_addresses(text: str, host: str, port: int) -> None:
    assert parse_live_address(text) == (host, port)
    assert parse_live_address(text).port == port


@pytest.mark.parametrize(
    "text", ["", "abc", "65536", "-1", ":8765", "host:", "host:port", "::1:8765", "[::1]", "[]:80", "a b:80", "1.5"]
)
def test_bad_addresses_are_one_line_config_errors(text: str) -> None:
    with pytest.raises(LiveAddressError) as info:
        parse_live_address(text)
    message = str(info.value)
    assert isinstance(info.value, ConfigError)
    assert "\n" not in message and "[HOST:]PORT" in message


@given(st.integers(0, 65535))
def test_any_port_alone_binds_loopback(port: int) -> None:
    assert parse_live_address(str(port)) == (DEFAULT_HOST, port)


@given(st.text(max_size=30))
def test_anything_parses_or_fails_in_one_line(text: str) -> None:
    try:
        host, port = parse_live_address(text)
    except LiveAddressError as exc:
        assert "\n" not in str(exc)
    else:
        assert host and 0 <= port <= 65535


@pytest.mark.parametrize(("host", "loopback"), [
    ("127.0.0.1", True), ("127.0.0.2", True), ("localhost", True), ("::1", True),
    ("0.0.0.0", False), ("::", False), ("192.0.2.7", False), ("no-such-host.invalid", False),
])
def test_loopback_classification(host: str, loopback: bool) -> None:
    assert is_loopback(host) is loopback


@pytest.mark.parametrize("host", ["0.0.0.0", "::", "192.0.2.7"])
def test_a_non_loopback_address_gets_one_warning_line_naming_it(host: str) -> None:
    """No address is bound here: the warning is built from the address alone."""
    address = LiveAddress(host, 8799)
    line = exposure_warning(address)
    assert line is not None and "\n" not in line
    assert shown(address) in line and "anyone" in line and "read-only" in line and "127.0.0.1" in line


@pytest.mark.parametrize("host", ["127.0.0.1", "127.0.0.2", "localhost", "::1"])
def test_loopback_addresses_get_no_warning(host: str) -> None:
    assert exposure_warning(LiveAddress(host, 8799)) is None


def test_check_bindable_names_a_busy_port_and_an_unknown_host() -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen(1)
        busy = LiveAddress("127.0.0.1", taken.getsockname()[1])
        with pytest.raises(LiveAddressError, match="in use") as info:
            check_bindable(busy)
        assert "\n" not in str(info.value) and shown(busy) in str(info.value)
    with pytest.raises(LiveAddressError, match="not known"):
        check_bindable(LiveAddress("no-such-host.invalid", 8799))
    check_bindable(LiveAddress("127.0.0.2", 0))  # a free loopback address passes
