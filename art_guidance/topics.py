"""Every ROS 2 topic name of the package, declared once (node-relative unless absolute).

The guidance node, the simulator node, the recorder, the bag rendering and the tests read
them from here; a namespace or a remapping applies to the relative ones as usual.
"""
from __future__ import annotations

NAV = "nav/relative_state"                  # in: navigation fix (RelativeNavState)
REPLAN_REQUEST = "guidance/replan_request"  # in: target and mode (ReplanRequest)
MANEUVER_PLAN = "guidance/maneuver_plan"    # out: plans and rejection notices (ManeuverPlan)
DIAGNOSTICS = "/diagnostics"                # out: decisions and statuses (DiagnosticArray)
SOLVE_RECORD = "guidance/solve_record"      # recorded only, never published (SolveRecord)

# visualisation (frame chief_rtn, `ros/visualization.py`)
PLAN_PATH = "guidance/viz/plan_path"        # nav_msgs/Path
PLAN_MARKERS = "guidance/viz/plan_markers"  # visualization_msgs/MarkerArray
DEPUTY_MARKERS = "guidance/viz/deputy"      # visualization_msgs/MarkerArray
DEPUTY_POSE = "guidance/viz/deputy_pose"    # geometry_msgs/PoseWithCovarianceStamped
TRUTH_PATH = "sim/viz/truth_path"           # the simulator's truth trajectory, nav_msgs/Path
