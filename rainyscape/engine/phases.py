"""Which of a method's phases a step is in (phases run in order; each ends at a fraction
of the run, the last at its end)."""

from __future__ import annotations

from dataclasses import dataclass

from rainyscape.config import PhaseConfig


@dataclass(frozen=True)
class PhaseSchedule:
    names: tuple[str, ...]
    configs: tuple[PhaseConfig, ...]
    ends: tuple[int, ...]  # first step after each phase

    @staticmethod
    def of(phases: dict[str, PhaseConfig], max_iters: int) -> "PhaseSchedule":
        ends = tuple(int(round(max_iters * p.end)) for p in phases.values())
        return PhaseSchedule(tuple(phases), tuple(phases.values()), ends[:-1] + (max_iters,))

    def at(self, step: int) -> tuple[str, PhaseConfig]:
        """The name and config of the phase that step ``step`` (0-based) belongs to."""
        for name, cfg, end in zip(self.names, self.configs, self.ends):
            if step < end:
                return name, cfg
        return self.names[-1], self.configs[-1]

    def length(self, name: str) -> int:
        """Number of steps phase ``name`` runs."""
        i = self.names.index(name)
        return max(0, self.ends[i] - (self.ends[i - 1] if i else 0))
