"""The proposal worker: the learned step of a plan, and SCVx* from its proposal, in a process
of its own (a lifecycle apart from one plan's).

`process.ProposalProcess` is the planner's side (start, submit, collect, dismiss, a stall or a
death replaced), `serve.serve` the worker's loop, `messages` the typed envelopes between them.
"""
