"""Records stored as they arrive: one JSON line per finished unit, appended and fsync'ed.

A run interrupted at any moment leaves every finished record on disk; at
worst the last line is torn, and :meth:`RecordStore.load` skips it. Records
are keyed by ``id``: a unit evaluated twice (a task re-run after a worker was
lost, a resumed run) is kept once, the first time.
"""

from __future__ import annotations

import json
import os
from pathlib import Path


class RecordStore:
    """Append-only JSON-lines file of records with unique ``id``."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.records: dict[str, dict] = {}
        self.duplicates = 0

    def load(self) -> RecordStore:
        if self.path.exists():
            data = self.path.read_bytes()
            if data and not data.endswith(b"\n"):  # torn last line: cut it so appends start clean
                with open(self.path, "r+b") as f:
                    f.truncate(data.rfind(b"\n") + 1)
            with open(self.path, encoding="utf-8") as f:
                for line in f:
                    try:
                        rec = json.loads(line)
                    except json.JSONDecodeError:
                        continue  # a line torn by an interruption: that unit runs again
                    if isinstance(rec, dict) and "id" in rec:
                        self.records.setdefault(rec["id"], rec)
        return self

    def add(self, records: list[dict]) -> list[dict]:
        """Append the records not yet stored (durably: flush + fsync); returns those added."""
        new = []
        for rec in records:
            if rec["id"] in self.records:
                self.duplicates += 1
                continue
            self.records[rec["id"]] = rec
            new.append(rec)
        if new:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            with open(self.path, "a", encoding="utf-8") as f:
                for rec in new:
                    f.write(json.dumps(rec, allow_nan=False, sort_keys=True) + "\n")
                f.flush()
                os.fsync(f.fileno())
        return new

    def __contains__(self, uid: str) -> bool:
        return uid in self.records

    def __len__(self) -> int:
        return len(self.records)
