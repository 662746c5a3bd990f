"""Shared main() body of the test helper nodes: init, spin until interrupted, clean up."""
from __future__ import annotations

from typing import Callable

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node


def spin_until_shutdown(make_node: Callable[[], Node], ready_text: str) -> int:
    """rclpy.init, build the node, print `ready_text`, spin; Jazzy-correct shutdown."""
    rclpy.init()
    node = make_node()
    print(ready_text, flush=True)
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0
