"""Mirror a run folder between a worker's local cache and object storage.

After every progress report the worker uploads what changed, so storage always holds the
run's completed frames: a job whose worker dies resumes from them on another machine.
The manifest goes up last, so a manifest in storage never lists a frame whose state file
is not there yet.
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass, field
from pathlib import Path

from fluidcore.names import safe_join
from fluidcore.runs import MANIFEST
from service.storage import Storage


def _content_type(path: Path) -> str:
    return {".mp4": "video/mp4", ".json": "application/json"}.get(path.suffix, "application/octet-stream")


def _is_temporary(path: Path) -> bool:
    return path.name.startswith(".") or path.name.endswith((".tmp", ".part"))


@dataclass
class FolderMirror:
    """Uploads the files of `folder` under `prefix`, each again only when its size or mtime changed."""

    storage: Storage
    folder: Path
    prefix: str
    _sent: dict[str, tuple[int, int]] = field(default_factory=dict)

    def push(self) -> list[str]:
        """Upload new and changed files (manifest last); returns their relative names."""
        changed = []
        for path in sorted(self.folder.rglob("*")):
            if not path.is_file() or _is_temporary(path):
                continue
            name = path.relative_to(self.folder).as_posix()
            stat = path.stat()
            if self._sent.get(name) != (stat.st_size, stat.st_mtime_ns):
                changed.append((name, path, (stat.st_size, stat.st_mtime_ns)))
        changed.sort(key=lambda item: item[0] == MANIFEST)
        for name, path, signature in changed:
            self.storage.put_file(f"{self.prefix}/{name}", path, _content_type(path))
            self._sent[name] = signature
        return [name for name, _, _ in changed]

    def pull(self) -> list[str]:
        """Replace the folder with what storage holds (storage is the truth: another worker may have
        gone further than this machine's cache); returns the names fetched."""
        shutil.rmtree(self.folder, ignore_errors=True)
        self.folder.mkdir(parents=True)
        self._sent.clear()
        fetched = []
        for info in self.storage.list(f"{self.prefix}/"):
            name = info.key[len(self.prefix) + 1 :]
            target = safe_join(self.folder, name)
            self.storage.get_file(info.key, target)
            stat = target.stat()
            self._sent[name] = (stat.st_size, stat.st_mtime_ns)
            fetched.append(name)
        return fetched
