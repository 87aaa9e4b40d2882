"""``--live [HOST:]PORT`` parsing: loopback by default, one-line errors."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from dobhil.errors import ConfigError
from dobhil.live import DEFAULT_HOST, LiveAddressError, parse_live_address


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
