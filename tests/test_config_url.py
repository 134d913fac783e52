"""Config device URLs: taken apart by the drivers' one parser (parse_device_url); the config
keeps only its own rules (scheme spelled out, a scheme the daemon runs, file:// path, unit/id)."""

from __future__ import annotations

import pytest
import yaml
from cgamap.daemon import config
from cgamap.daemon.config import check_url
from cgamap.drivers.transport import DeviceUrlError, parse_device_url
from hypothesis import given, settings
from hypothesis import strategies as st


@pytest.mark.parametrize("url", [
    "serial:///dev/serial/by-id/usb-FTDI-if00-port0?baudrate=38400",
    "SERIAL:///dev/ttyUSB0", "serial:///dev/ttyUSB0?baud=9600", "spy+serial:///dev/ttyUSB0",
    "tcp://192.168.0.10:502?unit=1", "tcp://[::1]:502?trace=1", "sim://hokuyo", "sim://",
    "file:///tmp/log.gz", "usb://"])
def test_good_urls(url):
    assert check_url(url) is None


@pytest.mark.parametrize("url, problem", [
    ("/dev/ttyUSB0", "a bare device path '/dev/ttyUSB0': write serial:///dev/ttyUSB0"),
    ("localhost:502", "no scheme in 'localhost:502'"),
    ("laser", "no scheme in 'laser'"),
    ("", "empty device URL"),
    ("http://example.org/laser", "unknown scheme 'http' in 'http://example.org/laser'"),
    ("serial:///", "no device path in 'serial:///'"),
    ("file://", "no device path in 'file://'"),
    ("serial://", "serial://: serial:// needs a device path"),
    ("tcp://h", "tcp://h: tcp:// needs host:port"),
    ("tcp://h:99999", "tcp://h:99999: malformed URL"),
    ("serial:///dev/x?baudrate=0", "baud rate 0 must be positive"),
    ("serial:///dev/x?baud=fast", "baud rate 'fast' is not a whole number"),
    ("tcp://h:502?unit=one", "query unit='one' must be an integer"),
    ("spy+sim://hokuyo", "spy+ (trace) is for serial:// and tcp:// devices, not sim://"),
    ("file:///x.log?trace=1", "not file://"),
])
def test_bad_urls_give_one_line(url, problem):
    msg = check_url(url)
    assert msg is not None and problem in msg and "\n" not in msg


_URLS = st.builds(
    "{}{}://{}{}".format,
    st.sampled_from(["", "spy+"]),
    st.sampled_from(config.URL_SCHEMES),
    st.sampled_from(["", "h", "h:0", "h:502", "h:x", "/dev/ttyS0", "/", "[::1]:2"]),
    st.sampled_from(["", "?baudrate=9600", "?baud=-3", "?baudrate=x", "?unit=2", "?id=x"]))


@settings(max_examples=150, deadline=None)
@given(_URLS)
def test_what_the_parser_rejects_the_config_rejects_in_its_words(url):
    """The config never accepts a URL the drivers' parser refuses, and reports the parser's
    own line for it: one parser, one wording."""
    try:
        parse_device_url(url)
    except DeviceUrlError as exc:
        assert check_url(url) == str(exc)


def test_carmen_scheme_comes_from_the_parser(tmp_path):
    def load(url: str) -> dict:
        p = tmp_path / "c.yaml"
        p.write_text(yaml.safe_dump({"devices": {"laser": {
            "role": "laser", "model": "carmen", "url": url}}}))
        return config.load(p)

    assert load("FILE:///data/intel.log")["devices"]["laser"]["url"] == "FILE:///data/intel.log"
    with pytest.raises(config.ConfigError, match="a carmen log needs a file:// URL"):
        load("tcp://h:1")
