"""Planning: request/result types, the post hoc check, `GuidancePipeline` and the replan policy.

Pure numpy (no ROS): the node, the CLI, the simulator's in-process link and the dataset tools
all plan through `GuidancePipeline.plan(request) -> PlanResult`.
"""
