"""parse_device_url: the one parser of device URLs (transport, Modbus base, pan-tilt, LMS2xx)."""

from __future__ import annotations

import pytest
from cgamap.drivers.transport import (
    DeviceUrl,
    DeviceUrlError,
    TransportError,
    parse_device_url,
)
from hypothesis import given
from hypothesis import strategies as st


@pytest.mark.parametrize("url, want", [
    ("/dev/ttyUSB0", dict(scheme="serial", path="/dev/ttyUSB0")),
    ("/dev/ttyUSB0?baud=500000", dict(scheme="serial", path="/dev/ttyUSB0", baud=500000)),
    ("serial:///dev/ttyS0?baudrate=38400", dict(scheme="serial", path="/dev/ttyS0", baud=38400)),
    ("serial://dev/ttyS0", dict(scheme="serial", path="/dev/ttyS0")),
    ("SERIAL:///dev/ttyS0", dict(scheme="serial", path="/dev/ttyS0")),
    ("rtu:///dev/pts/7", dict(scheme="rtu", path="/dev/pts/7")),
    ("tcp://10.0.0.2:502?unit=7", dict(scheme="tcp", host="10.0.0.2", port=502,
                                       options={"unit": "7"})),
    ("127.0.0.1:5020", dict(scheme="tcp", host="127.0.0.1", port=5020, url="tcp://127.0.0.1:5020")),
    ("localhost:4001?unit=3", dict(scheme="tcp", host="localhost", port=4001,
                                   options={"unit": "3"})),
    ("socket://h:1", dict(scheme="socket", host="h", port=1)),
    ("rtu+tcp://h:2", dict(scheme="rtu+tcp", host="h", port=2)),
    ("tcp://[::1]:502", dict(scheme="tcp", host="::1", port=502)),
    ("spy+serial:///dev/x", dict(scheme="serial", path="/dev/x", spy=True, url="serial:///dev/x")),
    ("spy+/dev/x", dict(scheme="serial", path="/dev/x", spy=True)),
    ("/dev/x?trace=1&exclusive=1", dict(path="/dev/x", spy=True, options={"exclusive": "1"})),
    ("loop://?x=1", dict(scheme="loop", path="loop://", options={"x": "1"})),
    ("usb://", dict(scheme="usb", path="usb://")),
    # baudrate wins over baud; the last value of a repeated option wins
    ("/dev/x?baud=9600&baudrate=19200", dict(baud=19200)),
    ("/dev/x?baud=9600&baud=38400", dict(baud=38400)),
])
def test_good_forms(url, want):
    u = parse_device_url(url)
    for name, value in want.items():
        got = dict(u.options) if name == "options" else getattr(u, name)
        assert got == value, (url, name, got)
    assert isinstance(u, DeviceUrl)


def test_defaults_and_address():
    u = parse_device_url("tcp://[::1]:502")
    assert u.is_network and u.address == "[::1]:502" and u.baud is None and not u.spy
    u = parse_device_url("/dev/ttyACM0")
    assert not u.is_network and u.port is None and dict(u.options) == {}
    with pytest.raises(TypeError):
        u.options["x"] = "1"              # read-only
    with pytest.raises(AttributeError):
        u.path = "/dev/other"             # frozen


@pytest.mark.parametrize("url, needle", [
    ("", "empty device URL"),
    ("   ", "empty device URL"),
    ("tcp://127.0.0.1", "needs host:port"),
    ("socket://", "needs host:port"),
    ("tcp://host:port", "malformed URL"),
    ("tcp://h:99999", "malformed URL"),
    ("tcp://h:0", "needs host:port"),
    ("serial://", "needs a device path"),
    ("/dev/x?baud=fast", "baud rate 'fast' is not a whole number"),
    ("/dev/x?baudrate=0", "baud rate 0 must be positive"),
    ("/dev/x?baud=-5", "must be positive"),
])
def test_bad_forms_name_the_url(url, needle):
    with pytest.raises(DeviceUrlError, match=needle) as ei:
        parse_device_url(url)
    msg = str(ei.value)
    assert "\n" not in msg and (url.split("?")[0] in msg if url.strip() else True)


def test_scheme_filter_and_error_class():
    with pytest.raises(TransportError, match="unknown URL scheme 'gopher://'") as ei:
        parse_device_url("gopher://x", ("serial", "tcp"), TransportError)
    assert "a device path, serial:// or tcp://host:port" in str(ei.value)
    assert "unsupported scheme" in str(ei.value)
    with pytest.raises(DeviceUrlError, match="unknown URL scheme"):
        parse_device_url("/dev/x", ("tcp",))          # a plain path is a serial URL
    assert parse_device_url("/dev/x", ("serial",)).path == "/dev/x"
    assert issubclass(DeviceUrlError, ValueError)


@given(host=st.from_regex(r"[a-z][a-z0-9\-]{0,20}(\.[a-z0-9]{1,8}){0,3}", fullmatch=True),
       port=st.integers(1, 65535), baud=st.integers(1, 4_000_000),
       scheme=st.sampled_from(["tcp", "socket", "rtu+tcp", "modbus+tcp"]))
def test_network_round_trip(host, port, baud, scheme):
    u = parse_device_url(f"{scheme}://{host}:{port}?baud={baud}&unit=2")
    assert (u.scheme, u.host, u.port, u.baud, dict(u.options)) == \
        (scheme, host, port, baud, {"unit": "2"})
    assert parse_device_url(u.address).address == u.address     # bare host:port reads back


@given(path=st.from_regex(r"(/[A-Za-z0-9_.\-]{1,12}){1,4}", fullmatch=True),
       spy=st.booleans(), form=st.sampled_from(["{p}", "serial://{p}"]))
def test_path_round_trip(path, spy, form):
    url = ("spy+" if spy else "") + form.format(p=path)
    u = parse_device_url(url)
    assert (u.scheme, u.path, u.spy, u.host, u.port) == ("serial", path, spy, "", None)
