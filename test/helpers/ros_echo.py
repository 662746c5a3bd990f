"""A separate process that echoes art_guidance_msgs messages back: `<type>_in` -> `<type>_out`."""
import sys

from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy

from art_guidance_msgs.msg import ManeuverPlan, RelativeNavState, ReplanRequest, SolveRecord
from helpers.spin_main import spin_until_shutdown

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
    return spin_until_shutdown(Echo, "echo ready")


if __name__ == "__main__":
    sys.exit(main())
