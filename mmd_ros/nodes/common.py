"""What every mmd node shares: common parameters, the device and model, latched topics, main().

Every node runs on rclpy's ``EventsExecutor`` (measured on this machine: the standard
single-threaded executor loses 15–28 % of the messages at 1 kHz). Per-sample work at 1 kHz
never runs in an rclpy timer: the terminal stage blocks on the USB transport in its own thread,
and the downstream nodes work in their subscription callbacks.
"""

from __future__ import annotations

import re
import signal
import sys
import threading
from collections.abc import Callable
from typing import Any

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.experimental import EventsExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions

from mmd_ros.core.device import DeviceDescription, find_config, load_device
from mmd_ros.core.errors import MmdError
from mmd_ros.core.model import Model, load_model
from mmd_ros.nodes.params import Param, ParameterError

__all__ = ['COMMON_PARAMS', 'MODEL_PARAMS', 'NAMESPACE', 'load_device_param',
           'load_model_param', 'request_stop', 'run', 'spin']

#: GIL switch interval of the node processes [s] (Python's default is 0.005).
SWITCH_INTERVAL_S = 0.0005

#: Default namespace of every node; relative topic names follow it (-r __ns:=/cell3/mmd).
NAMESPACE = 'mmd'

COMMON_PARAMS = [
    Param('device_file', 'mmd_prototype.yaml', 'device description (a path, or a file name in '
          'the package\'s config/)'),
    Param('qos', 'reliable', 'QoS of the per-sample topics: reliable (deep queue, nothing lost '
          'while the reader keeps up) or sensor (best effort, newest first)',
          choices=('reliable', 'sensor')),
    Param('qos_depth', 1000, 'queue depth of reliable per-sample topics [messages]',
          low=10, high=100000),
    Param('diagnostics_period_s', 1.0, 'period of /diagnostics [s]', low=0.1, high=60.0),
]

MODEL_PARAMS = [
    Param('model_file', '', 'model file (YAML: thermal mode, model terms, uncertainty); "" '
          'the default model (CDF + thermal compensation)'),
]


def load_device_param(name: str) -> DeviceDescription:
    """The device description named by the ``device_file`` parameter."""
    try:
        return load_device(find_config(name))
    except FileNotFoundError as exc:
        raise ParameterError(f'parameter device_file: {exc}') from None


def load_model_param(path: str) -> Model:
    """The model named by the ``model_file`` parameter ('' the default model)."""
    if not path:
        return Model()
    try:
        return load_model(path)
    except FileNotFoundError as exc:
        raise ParameterError(f'parameter model_file: {exc}') from None


_STOP = threading.Event()


def request_stop() -> None:
    """End the node as SIGINT does: the spin loop ends between two callbacks, then the node is
    destroyed while its context is valid (from any thread; shutting the context down from
    another thread instead can fail a timer's publish in the middle of its callback)."""
    _STOP.set()


def _request_stop(signum: int, frame: Any) -> None:
    """SIGINT / SIGTERM: leave the spin loop at the next turn (no exception inside a callback)."""
    request_stop()


def spin(node: Node) -> None:
    """``rclpy.spin`` on an EventsExecutor, returning after Ctrl-C, SIGTERM or a shutdown.

    (``EventsExecutor.spin()`` and ``spin_once()`` without a timeout do not always wake up when
    the context is shut down, measured with rclpy 7.1.6: poll with a timeout.)
    """
    executor = EventsExecutor(context=node.context)
    executor.add_node(node)
    try:
        while node.context.ok() and not _STOP.is_set():
            executor.spin_once(timeout_sec=0.1)
    finally:
        executor.remove_node(node)


def run(factory: Callable[[], Node], args: list[str] | None = None) -> int:
    """The Jazzy node life cycle: init, spin on an EventsExecutor until Ctrl-C / SIGTERM /
    shutdown, then destroy the node (which stops its threads and closes its files) and shut
    down. SIGINT and SIGTERM end the spin loop between two callbacks, so that the node is
    destroyed while its context is still valid (a recorder closes its log cleanly)."""
    # A thread waiting for the GIL waits up to the switch interval (5 ms by default) while
    # another runs Python: at 1 kHz the terminal reader must not wait that long.
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    _STOP.clear()
    previous = {sig: signal.signal(sig, _request_stop) for sig in (signal.SIGINT, signal.SIGTERM)}
    node: Node | None = None
    status = 0
    try:
        node = factory()
        spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (MmdError, ValueError) as exc:
        name = re.sub(r'(?<!^)(?=[A-Z])', '_', getattr(factory, '__name__', 'Node')).lower()
        print(f'{name}: error: {exc}', file=sys.stderr)
        status = 2
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return status


def values_of(params: list[Param], values: dict[str, Any]) -> dict[str, Any]:
    return {p.name: values[p.name] for p in params}
