"""Guidance: the receding-horizon loop one floor above the planner.

`core.GuidanceCore` takes fixes and targets, decides with the replan policy
(`replan.ReplanPolicy`: when to replan, over which window, what to carry) and the end game
(`planning.endgame`) whether a replan is made and put in force, and plans through
`planning.GuidancePipeline`; the node (`ros/`) and the in-process simulator link (`sim/`) drive
it. Nothing in `planning/` imports it.
"""
