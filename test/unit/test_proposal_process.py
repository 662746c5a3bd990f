"""The proposal worker process: a worker that cannot start is reported and not restarted at
every plan (the plans meanwhile propose in line)."""
from __future__ import annotations

import time

from art_guidance.config import GuidanceConfig
from art_guidance.planning import proposal_process
from art_guidance.planning.proposal_process import ProposalProcess


def test_a_worker_that_cannot_load_its_model_is_not_restarted_at_once(tmp_path, monkeypatch):
    config = GuidanceConfig.load()
    model = (str(tmp_path / "missing.pt"), "0" * 64, 1, (1.0,))
    worker = ProposalProcess()
    try:
        assert worker.start(config.to_json(), config.sha256(), model) is False
        assert "missing.pt" in worker.error and not worker.alive
        job = {"config": config.to_json(), "config_sha256": config.sha256(), "model": model}
        assert worker.submit(job) is False and not worker.alive  # declined, nothing spawned
        assert "missing.pt" in worker.error  # the reason stays
        monkeypatch.setattr(proposal_process, "RESTART_AFTER_S", 0.0)
        assert worker.submit(job) is False and worker.alive  # started again, in the background
        assert worker.error == "the worker process is starting"
        deadline = time.monotonic() + 60.0
        while worker.alive and time.monotonic() < deadline:  # it fails again
            assert worker.submit(job) is False
            time.sleep(0.2)
        assert "missing.pt" in worker.error
    finally:
        worker.close()
