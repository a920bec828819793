"""How a run and a step end, as enums (OpenHTF's ``PhaseResult`` is the model).

The members are ``StrEnum``: each *is* its stored string ("completed", "done", ...), so stores,
JSON documents and the API keep the same values.

* ``RunOutcome``: the engine's final status of a run.  The database stores ``stopped`` as
  ``completed`` with ``live["outcome"] = "stopped"`` (a stopped run ended cleanly, early).
* ``StepOutcome``: a step's status in the store: ``running`` while it executes, then one outcome.
"""
from __future__ import annotations

from enum import StrEnum


class RunOutcome(StrEnum):
    COMPLETED = "completed"      # every step ran to its end
    STOPPED = "stopped"          # an operator stop: the current step ended early, then safe state
    ABORTED = "aborted"          # abort now (operator, interrupt, suspension cap), safe state
    FAILED = "failed"            # an error ended the run (safe state too)


class StepOutcome(StrEnum):
    RUNNING = "running"
    DONE = "done"
    STOPPED = "stopped"
    ABORTED = "aborted"
    FAILED = "failed"

    @classmethod
    def ending_run(cls, run: RunOutcome) -> "StepOutcome":
        """Status of the step that was executing when the run ended with ``run``."""
        return {RunOutcome.STOPPED: cls.STOPPED, RunOutcome.ABORTED: cls.ABORTED}.get(run, cls.FAILED)
