"""Each protocol says which timeout its drive keeps on the host's frames
(``DriveProtocol.host_watch``), read from the profile before any bus opens; one generic
rule (``dobhil.runtime.session.check_host_watch``) holds the loop period to half of it.
Every shipped profile's answer, and the rule's edge."""

from __future__ import annotations

import math
import re

import pytest

from dobhil.drives.load import load_profile
from dobhil.drives.registry import protocol
from dobhil.errors import ConfigError
from dobhil.runtime.session import check_host_watch

#: shipped profile -> (the setting that holds its drive's timeout on the host, seconds); None: none
SHIPPED = {
    "odrive-0.6": ("watchdog_timeout", 0.05),
    "odrive-0.5": ("watchdog_timeout", 0.05),
    "odrive-0.6-factory": None,                     # the watchdog off
    "moteus-r4.11": ("watchdog_timeout", 0.1),       # register 0x027
    "epos4": ("cia402.consumer_heartbeat", 0.1),      # 0x1016
    "cia402-emulated": None,                          # consumer off
    "mini-cheetah": ("command_timeout", 0.025),       # its firmware's CAN_TIMEOUT
    "ak80-9": None,                                   # none documented by CubeMars
    "dm4310": None,                                   # TIMEOUT register 0 from the factory
}


@pytest.mark.parametrize("name", SHIPPED)
def test_each_shipped_profile_names_its_drives_timeout_on_the_host(name: str) -> None:
    profile = load_profile(name)
    watch = protocol(profile.protocol).host_watch(profile)
    expected = SHIPPED[name]
    if expected is None:
        assert watch is None
        check_host_watch(profile, 10.0)   # no limit from it
        return
    assert watch is not None and (watch.key, watch.timeout) == expected
    half = watch.timeout / 2
    check_host_watch(profile, math.nextafter(half, 0.0))   # just under half: allowed
    with pytest.raises(ConfigError, match=rf"^loop.period = {half:g} s is too long for the {re.escape(watch.what)} "):
        check_host_watch(profile, half)
