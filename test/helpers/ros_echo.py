"""A separate process that echoes art_guidance_msgs messages back: `<type>_in` -> `<type>_out`."""
import sys

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy

from art_guidance_msgs.msg import ManeuverPlan, RelativeNavState, ReplanRequest, SolveRecord

TYPES = {"nav": RelativeNavState, "plan": ManeuverPlan, "replan": ReplanRequest,
         "record": SolveRecord}


class Echo(Node):
    def __init__(self) -> None:
        super().__init__("art_guidance_test_echo")
        qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        self._pubs = {}
        for name, msg_type in TYPES.items():
            self._pubs[name] = self.create_publisher(msg_type, f"echo/{name}_out", qos)
            self.create_subscription(msg_type, f"echo/{name}_in",
                                     lambda msg, n=name: self._pubs[n].publish(msg), qos)


def main() -> int:
    rclpy.init()
    node = Echo()
    print("echo ready", flush=True)
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
