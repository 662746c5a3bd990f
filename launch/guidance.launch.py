"""Launch the art_guidance guidance node, plain or managed (lifecycle), as Nav2's launch files do.

    ros2 launch art_guidance guidance.launch.py
    ros2 launch art_guidance guidance.launch.py managed:=true autostart:=true namespace:=chaser
    ros2 launch art_guidance guidance.launch.py params_file:=my_params.yaml record_dir:=/data/bag

Arguments (`ros2 launch art_guidance guidance.launch.py --show-args` lists them):

- `params_file`: the node's parameter YAML (default: the installed config/guidance_node.yaml,
  the node's own defaults); the planning YAML files are chosen by its `config_dir` parameter.
- `namespace`: namespace of the node and its relative topics (default: none).
- `use_sim_time`: take time from /clock (default: false).
- `log_level`: the node's log level (debug, info, warn, error, fatal; default: info).
- `managed`: true runs the lifecycle node `guidance_managed_node` (it starts unconfigured),
  false the plain `guidance_node` (default: false).
- `autostart`: with `managed`, configure the node at start and activate it once it is inactive
  (default: true); false leaves the transitions to the caller (`ros2 lifecycle set`).
- `use_respawn`: restart the node 2 s after it exits (default: false).
- `record_dir`: bag folder of the recording (default: '' = the parameter file's, whose default is
  <ROS_HOME>/art_guidance_logs/<run>).
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchContext, LaunchDescription
from launch.actions import DeclareLaunchArgument, EmitEvent, OpaqueFunction, RegisterEventHandler
from launch.events import matches_action
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import LifecycleNode, Node
from launch_ros.event_handlers import OnStateTransition
from launch_ros.events.lifecycle import ChangeState
from lifecycle_msgs.msg import Transition

PACKAGE = "art_guidance"
NODE_NAME = "guidance_node"  # the name both executables give their node (the YAML's key)
RESPAWN_DELAY_S = 2.0
# SIGINT lets the node finish the solve in flight (solve_deadline_s, 5 s by default), publish and
# record it, and stop the proposal worker: launch waits this long before SIGTERM (which the node
# handles the same way), then as long again before SIGKILL (the recording survives even that)
STOP_TIMEOUT_S = "15"


def _arguments() -> list:
    share = get_package_share_directory(PACKAGE)
    return [
        DeclareLaunchArgument("params_file",
                              default_value=os.path.join(share, "config", "guidance_node.yaml"),
                              description="parameter YAML of the guidance node"),
        DeclareLaunchArgument("namespace", default_value="",
                              description="namespace of the node and its topics"),
        DeclareLaunchArgument("use_sim_time", default_value="false",
                              description="use simulation (/clock) time"),
        DeclareLaunchArgument("log_level", default_value="info",
                              description="log level (debug, info, warn, error, fatal)"),
        DeclareLaunchArgument("managed", default_value="false",
                              description="run the lifecycle node guidance_managed_node"),
        DeclareLaunchArgument("autostart", default_value="true",
                              description="managed: configure and activate at start"),
        DeclareLaunchArgument("use_respawn", default_value="false",
                              description="restart the node if it exits"),
        DeclareLaunchArgument("record_dir", default_value="",
                              description="bag folder ('' = the parameter file's)"),
    ]


def _flag(context: LaunchContext, name: str) -> bool:
    value = LaunchConfiguration(name).perform(context).strip().lower()
    if value not in ("true", "false"):
        raise ValueError(f"launch argument {name} must be true or false, got {value!r}")
    return value == "true"


def _nodes(context: LaunchContext) -> list:
    """The node (plain or lifecycle) and, for a managed node with autostart, its transitions;
    built once the arguments are known, so that an empty record_dir overrides nothing."""
    parameters: list = [LaunchConfiguration("params_file").perform(context),
                        {"use_sim_time": _flag(context, "use_sim_time")}]
    record_dir = LaunchConfiguration("record_dir").perform(context)
    if record_dir:
        parameters.append({"record_dir": record_dir})
    common = dict(name=NODE_NAME, namespace=LaunchConfiguration("namespace").perform(context),
                  output="screen", parameters=parameters,
                  respawn=_flag(context, "use_respawn"), respawn_delay=RESPAWN_DELAY_S,
                  sigterm_timeout=STOP_TIMEOUT_S, sigkill_timeout=STOP_TIMEOUT_S,
                  ros_arguments=["--log-level", LaunchConfiguration("log_level").perform(context)])
    if not _flag(context, "managed"):
        return [Node(package=PACKAGE, executable="guidance_node", **common)]
    node = LifecycleNode(package=PACKAGE, executable="guidance_managed_node", **common)
    if not _flag(context, "autostart"):
        return [node]

    def change(transition: int) -> EmitEvent:
        return EmitEvent(event=ChangeState(lifecycle_node_matcher=matches_action(node),
                                           transition_id=transition))

    activate = RegisterEventHandler(OnStateTransition(
        target_lifecycle_node=node, goal_state="inactive",
        entities=[change(Transition.TRANSITION_ACTIVATE)]))
    return [node, activate, change(Transition.TRANSITION_CONFIGURE)]


def generate_launch_description() -> LaunchDescription:
    return LaunchDescription([*_arguments(), OpaqueFunction(function=_nodes)])
