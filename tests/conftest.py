"""Shared test set-up: every device test runs on the CPU and on the first GPU where there is one."""

import os
import signal
import sys

import pytest
import warp as wp

sys.path.insert(0, os.path.dirname(__file__))  # the float64 reference lives beside the tests

wp.config.quiet = True
wp.init()

# POLYDEM_TEST_DEVICES=cuda:0 runs on the GPU only (the GPU machine's Warp bundle has no CPU compiler).
_env = os.environ.get("POLYDEM_TEST_DEVICES")
# The Ctrl-C tests (test_cli.py) need SIGINT delivered, to this process and to the commands it spawns; a suite
# started in the background of a non-interactive shell (`bash .ci/run &`) inherits it ignored, as a command run
# so should: restore Python's handler here (an exec resets a caught signal to its default in the children).
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)

DEVICES = _env.split(",") if _env else ["cpu"] + (["cuda:0"] if wp.get_cuda_device_count() > 0 else [])


def pytest_generate_tests(metafunc):
    if "device" in metafunc.fixturenames:
        metafunc.parametrize("device", DEVICES)


@pytest.fixture(scope="session")
def devices():
    return DEVICES
