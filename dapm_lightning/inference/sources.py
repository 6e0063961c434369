"""What to predict, as users have it: folders (searched recursively), glob patterns, files, ``.txt`` lists.

:func:`resolve_sources` turns any number of SOURCE arguments into :class:`SourceFile` s, images and videos, each
with an output name that is unique in the run and says where the file came from: a file found in a folder or by a
pattern is named by its path below that folder (``100MEDIA/DJI_0001.JPG`` -> ``100MEDIA_DJI_0001``), a file given
by itself by its stem. Extensions are matched regardless of case (``.JPG``), hidden files and folders (``.Trashes``,
macOS's ``._DJI_0001.JPG``) are left out, and so are the pictures an earlier predict run wrote into a folder a
folder or pattern reaches (a folder marked as a run's output, :func:`~dapm_lightning.inference.run_folder.
is_output_folder`), with one note naming the folder.
"""

from __future__ import annotations

import glob
import re
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from dapm_lightning.data.uapd import IMAGE_SUFFIXES
from dapm_lightning.inference.run_folder import is_output_folder, written_by_predict

VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg", ".wmv")
LIST_SUFFIX = ".txt"
"""A SOURCE with this extension is a list of paths, one a line (blank lines and ``#`` comments skipped)."""
FRAME_NAME = re.compile(r"(.+)_f\d{6,}")
"""A video frame's output name: the video's name, ``_f`` and the frame number (6 digits at least)."""
SourceKind = Literal["image", "video"]
Sources = str | Path | Sequence[str | Path]
"""One SOURCE or several."""


@dataclass(frozen=True)
class SourceFile:
    """One file to predict: its ``path``, its output ``name`` (a video's frames add ``_f<frame>``), ``kind``."""

    path: Path
    name: str
    kind: SourceKind


def has_magic(text: str) -> bool:
    """Whether ``text`` is a glob pattern."""
    return any(c in text for c in "*?[")


def file_kind(path: Path) -> SourceKind | None:
    """``image`` or ``video`` from the extension (any case), else None."""
    suffix = path.suffix.lower()
    return "image" if suffix in IMAGE_SUFFIXES else "video" if suffix in VIDEO_SUFFIXES else None


def as_list(sources: Sources) -> list[str | Path]:
    """``sources`` as a list of SOURCE arguments."""
    return [sources] if isinstance(sources, (str, Path)) else list(sources)


def case_free(pattern: str) -> str:
    """A glob pattern whose last component matches regardless of case (``*.jpg`` finds ``DJI_0001.JPG``)."""
    head, sep, last = pattern.rpartition("/")
    out, depth = [], 0
    for c in last:
        depth += c == "["
        depth -= c == "]" and depth > 0
        out.append(f"[{c.lower()}{c.upper()}]" if c.isalpha() and depth == 0 and c.lower() != c.upper() else c)
    return head + sep + "".join(out)


def _hidden(path: Path, root: Path) -> bool:
    return any(part.startswith(".") for part in path.relative_to(root).parts)


def _named(path: Path, root: Path | None) -> tuple[Path, str]:
    """``path`` with its output name: the path below ``root`` joined with ``_``, or the stem."""
    if root is None:
        return path, path.stem
    relative = path.relative_to(root)
    return path, "_".join((*relative.parent.parts, relative.stem))


def _run_outputs(paths: list[Path]) -> tuple[list[Path], list[str], list[Path]]:
    """``paths`` less the pictures predict wrote into a run's output folder; a note per such folder; the folders.

    A run's outputs (depth maps, sky masks, its contact sheet) are not drone images: a later run given a folder
    or pattern that reaches them leaves them out (:func:`~dapm_lightning.inference.run_folder.is_output_folder`).
    """
    marked: dict[Path, bool] = {}
    kept: list[Path] = []
    left: Counter[Path] = Counter()
    for p in paths:
        if written_by_predict(p.name) and file_kind(p):
            if p.parent not in marked:
                marked[p.parent] = is_output_folder(p.parent)
            if marked[p.parent]:
                left[p.parent] += 1
                continue
        kept.append(p)
    notes = [f"{folder}: a predict output folder, its {count} picture(s) written by predict left out (depth maps, "
             "not drone images); name them one by one to predict them anyway" for folder, count in left.items()]
    return kept, notes, list(left)


def _output_folder_fix(folders: list[Path]) -> str:
    return (f"{folders[0]} is a predict output folder (a run's depth maps, sky masks and contact sheet, not drone "
            "images): give the folder of the images it was predicted from")


def _folder(path: Path) -> tuple[list[tuple[Path, str]], list[str]]:
    """A folder's images, sub-folders included; notes on what it also holds.

    The videos it holds are noted, not predicted; so are the predict output folders in it (their pictures left out).
    """
    files, notes, outputs = _run_outputs(sorted(p for p in path.rglob("*") if p.is_file() and not _hidden(p, path)))
    images = [_named(p, path) for p in files if file_kind(p) == "image"]
    videos = [p.relative_to(path).as_posix() for p in files if file_kind(p) == "video"]
    if not images:
        fix = (f"give the video file itself, e.g. {path / videos[0]}" if videos
               else _output_folder_fix(outputs) if outputs
               else "give a folder that holds images, an image or a video, a glob such as 'DIR/*.JPG', or a .txt "
               "list of files")
        held = f" (it holds video(s) {', '.join(videos[:3])})" if videos else ""
        raise ValueError(f"{path}: no images ({', '.join(IMAGE_SUFFIXES)}, any case, sub-folders included){held}"
                         f"\nFix: {fix}")
    if videos:
        notes.append(f"{path}: {len(videos)} video(s) not predicted ({', '.join(videos[:2])}"
                     f"{', ...' if len(videos) > 2 else ''}): give a video as SOURCE to predict its frames")
    return images, notes


def _pattern(text: str) -> tuple[list[tuple[Path, str]], list[str]]:
    """The images and videos a glob pattern matches (extensions in any case), named below its root; notes.

    The predict output folders it reaches are noted, their pictures left out.
    """
    parts = Path(text).expanduser().parts
    first = next(k for k, part in enumerate(parts) if has_magic(part))
    root = Path(*parts[:first]) if first else Path(".")
    matches = sorted({Path(p) for p in glob.glob(case_free(str(Path(text).expanduser())), recursive=True)})
    files, notes, outputs = _run_outputs([p for p in matches if p.is_file() and file_kind(p) and not _hidden(p, root)])
    if not files:
        if outputs:
            raise FileNotFoundError(f"{text}: the pattern matches no image or video but a predict run's outputs\n"
                                    f"Fix: {_output_folder_fix(outputs)}")
        raise FileNotFoundError(f"{text}: the pattern matches no image or video ({len(matches)} other path(s))")
    return [_named(p, root) for p in files], notes


def _entry(text: str, origin: str = "") -> tuple[list[tuple[Path, str]], list[str]]:
    """One SOURCE (not a list): its files with their names, and notes."""
    path = Path(text).expanduser()
    if path.is_dir():
        return _folder(path)
    if path.is_file():
        if file_kind(path) is None:
            raise ValueError(f"{origin}{path}: neither an image ({', '.join(IMAGE_SUFFIXES)}) nor a video "
                             f"({', '.join(VIDEO_SUFFIXES)}), nor a {LIST_SUFFIX} list of paths")
        return [_named(path, None)], []
    if has_magic(text):
        try:
            return _pattern(text)
        except FileNotFoundError as error:
            raise FileNotFoundError(f"{origin}{error}") from None
    raise FileNotFoundError(f"{origin}{text}: no such file or folder (give folders of images, glob patterns such as "
                            f"'flight/**/*.jpg', images, videos or a {LIST_SUFFIX} list of paths)")


def is_list_file(source: str | Path) -> bool:
    """Whether a SOURCE is a ``.txt`` list of paths."""
    path = Path(source).expanduser()
    return path.is_file() and path.suffix.lower() == LIST_SUFFIX


def list_entries(path: Path) -> list[tuple[int, str, str]]:
    """A ``.txt`` list's entries: ``(line number, entry, path)``; a relative entry's path from the list's folder."""
    entries = []
    for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        entry = line.strip()
        if entry and not entry.startswith("#"):
            target = Path(entry).expanduser()
            entries.append((number, entry, str(target if target.is_absolute() else path.parent / target)))
    return entries


def _list_file(path: Path) -> tuple[list[tuple[Path, str]], list[str]]:
    """The entries of a ``.txt`` list, paths relative to the list's folder."""
    found: list[tuple[Path, str]] = []
    notes: list[str] = []
    for number, entry, text in list_entries(path):
        if entry.lower().endswith(LIST_SUFFIX):
            raise ValueError(f"{path} line {number}: {entry}: a list inside a list is not read")
        try:
            files, more = _entry(text, f"{path} line {number}: ")
        except FileNotFoundError as error:  # its own fix: the entry starts from the list's folder, not from here
            if "\nFix: " in str(error):
                raise
            raise FileNotFoundError(f"{error}\nFix: correct or remove line {number} of {path}; a relative path in a "
                                    f"list starts from the list's folder ({path.parent.resolve()}), not the "
                                    "current directory.") from None
        found += files
        notes += more
    if not found:
        raise ValueError(f"{path}: the list names no path (one image, video, folder or pattern a line)")
    return found, notes


def _unique_names(found: list[tuple[Path, str]]) -> list[tuple[Path, str]]:
    """Names made unique by their parent folders' names; two files that stay alike are refused."""
    names = [name for _, name in found]
    for level in range(1, 4):
        clashes = {n for n, count in Counter(names).items() if count > 1}  # counted once: linear in the files
        if not clashes:
            break
        names = [f"{found[k][0].parent.parts[-level]}_{n}"
                 if n in clashes and len(found[k][0].parent.parts) >= level else n for k, n in enumerate(names)]
    seen: dict[str, Path] = {}
    for (path, _), name in zip(found, names):
        if name in seen:
            raise ValueError(f"{path} and {seen[name]} would write the same output files (name {name!r}): "
                             "predict them in separate runs or rename one")
        seen[name] = path
    videos = {name: path for name, path in seen.items() if file_kind(path) == "video"}
    for name, path in seen.items():
        frame = FRAME_NAME.fullmatch(name) if videos else None
        if frame is not None and frame[1] in videos and file_kind(path) != "video":
            raise ValueError(f"{path} and a frame of {videos[frame[1]]} would write the same output files (name "
                             f"{name!r}): predict them in separate runs or rename one")
    return [(path, name) for (path, _), name in zip(found, names)]


def resolve_sources(sources: Sources) -> tuple[list[SourceFile], list[str]]:
    """Every file the SOURCE arguments name, in their order (each file once), and notes for the user.

    A folder gives its images, sub-folders included (videos in it are noted, not predicted); a glob pattern
    (``**`` recursive) its images and videos; an image or a video file itself; a ``.txt`` file the paths it
    lists, one a line, relative to its own folder. Raises ``FileNotFoundError`` / ``ValueError`` naming the
    source and saying what to give instead.
    """
    found: list[tuple[Path, str]] = []
    notes: list[str] = []
    for source in as_list(sources):
        files, more = _list_file(Path(source).expanduser()) if is_list_file(source) else _entry(str(source))
        found += files
        notes += more
    if not found:
        raise ValueError("no SOURCE given: name folders, images, videos, glob patterns or a .txt list")
    unique: dict[Path, tuple[Path, str]] = {}
    for path, name in found:
        unique.setdefault(path.resolve(), (path, name))
    named = _unique_names(list(unique.values()))
    return [SourceFile(p, n, file_kind(p) or "image") for p, n in named], notes


def resolve_source(source: Sources) -> tuple[Literal["images", "video"], list[Path]]:
    """What one SOURCE names: ``("video", [path])`` for a video alone, else ``("images", paths)``."""
    files, _ = resolve_sources(source)
    if len(files) == 1 and files[0].kind == "video":
        return "video", [files[0].path]
    return "images", [f.path for f in files if f.kind == "image"]
