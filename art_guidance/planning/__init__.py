"""Planning: request/result types, the post hoc check, `GuidancePipeline` and the replan policy.

Pure numpy (no ROS): the node, the CLI, the simulator's in-process link and the dataset tools
all plan through `GuidancePipeline.plan(request) -> PlanResult`.
"""

from art_guidance.planning.pipeline import GuidancePipeline
from art_guidance.config import PosthocThresholds
from art_guidance.planning.learned import posthoc_check
from art_guidance.planning.request import (
    NavState, PlanRequest, Target, WARM_STARTS, WarmStart, WarmStartSource,
)
from art_guidance.planning.result import (
    PlanResult, PosthocDecision, ScpAttempt, WarmStartProposal, WarmStartProvider,
)

__all__ = ["GuidancePipeline", "NavState", "PlanRequest", "PlanResult", "PosthocDecision",
           "PosthocThresholds", "ScpAttempt", "Target", "WARM_STARTS", "WarmStart",
           "WarmStartProposal", "WarmStartProvider", "WarmStartSource", "posthoc_check"]
