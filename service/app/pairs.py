"""Revisit pairs as the API and the console use them: list, label, read and delete the pairs
of an atlas, bound to the process's sessions (:mod:`service.app.revisit_pairs` does the
work)."""

from __future__ import annotations

from sqlalchemy.orm import Session, sessionmaker

from service.app import revisit_pairs
from service.app.revisit_pairs import PairFilter, PairRow


class RevisitPairs:
    """The pair use cases of one process."""

    def __init__(self, sessions: sessionmaker[Session]) -> None:
        self.sessions = sessions

    def list(self, atlas: str, where: PairFilter, limit: int = 100) -> list[PairRow]:
        """Newest first."""
        return revisit_pairs.list_pairs(self.sessions, atlas=atlas, where=where, limit=limit)

    def label(self, atlas: str, frame_id: int, other: int) -> PairRow:
        """Label two frames of the atlas as one place (an operator's pair); the new row."""
        pair_id = revisit_pairs.label_pair(
            self.sessions, atlas=atlas, frame_id=frame_id, other=other
        )
        return self.get(atlas, pair_id)

    def get(self, atlas: str, pair_id: int) -> PairRow:
        return revisit_pairs.get_pair(self.sessions, atlas=atlas, pair_id=pair_id)

    def delete(self, atlas: str, pair_id: int) -> None:
        revisit_pairs.delete_pair(self.sessions, atlas=atlas, pair_id=pair_id)
