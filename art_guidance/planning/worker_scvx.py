"""SCVx* from the learned proposal of one plan, solved in the proposal worker process
(`proposal_process.ProposalProcess`)."""
from __future__ import annotations

from art_guidance.deadline import Deadline
from art_guidance.optim import ScpResult
from art_guidance.planning.proposal_process import (
    GRACE_S, NO_DEADLINE_TIMEOUT_S, ProposalProcess,
)


class WorkerScvx:
    """SCVx* from the proposal of one plan, solved in the proposal worker: taken where the plan
    needs it (`result`), cancelled otherwise (`dismiss`)."""

    def __init__(self, worker: ProposalProcess, job_id: int) -> None:
        self._worker, self._job_id = worker, job_id
        self._taken = False

    def result(self, deadline: Deadline | None) -> ScpResult | None:
        """The worker's run (waiting for it within the plan's deadline and `GRACE_S`), or None:
        the plan solves it in line."""
        self._taken = True
        wait = NO_DEADLINE_TIMEOUT_S if deadline is None else deadline.left_s() + GRACE_S
        return self._worker.scvx_result(self._job_id, wait)

    def dismiss(self) -> None:
        """Cancel the run if the plan did not take it."""
        if not self._taken:
            self._worker.dismiss(self._job_id)

    def __enter__(self) -> "WorkerScvx":
        return self

    def __exit__(self, *exc: object) -> None:
        self.dismiss()
