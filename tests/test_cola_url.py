"""CoLa device URLs: the default port and the auto protocol come from parse_device_url."""

from __future__ import annotations

import pytest
from cgamap.drivers.cola import ColaDriver
from cgamap.drivers.transport import DeviceUrlError


@pytest.mark.parametrize("url, expect, protocol", [
    ("host", "tcp://host:2111", "A"),
    ("host:2112", "tcp://host:2112", "B"),
    ("tcp://host", "tcp://host:2111", "A"),
    ("tcp://10.0.0.5:2112", "tcp://10.0.0.5:2112", "B"),
    ("socket://host", "socket://host:2111", "A"),
    ("spy+tcp://host?trace=1", "spy+tcp://host:2111?trace=1", "A"),
    ("spy+host:2112", "spy+tcp://host:2112", "B"),
    ("spy://host:2112", "spy+tcp://host:2112", "B"),
    ("tcp://[::1]", "tcp://[::1]:2111", "A"),
    ("tcp://[::1]:2112", "tcp://[::1]:2112", "B"),
    ("serial:///dev/ttyUSB0?baudrate=115200", "serial:///dev/ttyUSB0?baudrate=115200", "A"),
])
def test_default_port_and_auto_protocol(url, expect, protocol):
    drv = ColaDriver(url)           # constructing does not connect
    assert drv.url == expect
    assert drv.protocol == protocol


def test_explicit_protocol_wins_over_the_port():
    assert ColaDriver("tcp://host:2112", protocol="A").protocol == "A"
    assert ColaDriver("host", protocol="b").protocol == "B"


@pytest.mark.parametrize("url, needle", [
    ("tcp://127.0.0.1:99999", "tcp://127.0.0.1:99999"),
    ("tcp://host:abc", "tcp://host:abc"),
    ("/dev/ttyUSB0", "/dev/ttyUSB0: read as tcp:///dev/ttyUSB0"),
])
def test_malformed_url_is_one_line_value_error_naming_it(url, needle):
    with pytest.raises(DeviceUrlError) as info:
        ColaDriver(url)
    assert isinstance(info.value, ValueError)
    msg = str(info.value)
    assert msg.startswith(needle) and "\n" not in msg
