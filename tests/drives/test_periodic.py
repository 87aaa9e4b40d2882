"""native_periodic: which buses send periodic frames outside this process's Python threads."""

from __future__ import annotations

from typing import Any
from unittest import mock

import can
import pytest

from dobhil.drives.periodic import native_periodic


class _Wrapper(can.BusABC):
    """A bus wrapper as a user writes one: forwards frames, not the periodic send."""

    def __init__(self, inner: can.BusABC, **kwargs: Any) -> None:
        self.inner = inner
        super().__init__(channel=inner.channel_info, **kwargs)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.inner.send(msg, timeout)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        return self.inner.recv(timeout), False


class _ForwardingWrapper(_Wrapper):
    """A wrapper that forwards the periodic send to its inner bus, and says so."""

    @property
    def native_periodic(self) -> bool:
        return native_periodic(self.inner)


class _Native(_Wrapper):
    native_periodic = True


def test_socketcan_is_native_by_its_class() -> None:
    socketcan = pytest.importorskip("can.interfaces.socketcan")
    # no AF_CAN here: an instance that was never opened (BusABC says it is shut down)
    bus = socketcan.SocketcanBus.__new__(socketcan.SocketcanBus)
    assert native_periodic(bus) is True


def test_virtual_bus_is_not_native() -> None:
    with can.Bus(interface="virtual", channel="periodic-test") as bus:
        assert native_periodic(bus) is False


def test_a_class_attribute_says_native() -> None:
    with can.Bus(interface="virtual", channel="periodic-test") as inner, _Native(inner) as bus:
        assert native_periodic(bus) is True


def test_a_wrapper_is_native_only_when_it_forwards() -> None:
    with can.Bus(interface="virtual", channel="periodic-test") as inner:
        with _Wrapper(inner) as plain:
            assert native_periodic(plain) is False
        with _Native(inner) as native, _ForwardingWrapper(native) as forwarding:
            assert native_periodic(forwarding) is True
        with _ForwardingWrapper(inner) as forwarding_virtual:
            assert native_periodic(forwarding_virtual) is False


def test_only_true_counts() -> None:
    """A mock (every attribute truthy) or a string is not a promise of native sending."""
    assert native_periodic(mock.Mock(spec=can.BusABC)) is False
    assert native_periodic(mock.Mock()) is False
    assert native_periodic(type("B", (), {"native_periodic": "yes"})()) is False
