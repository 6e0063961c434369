"""What to predict, as users have it: folders (searched recursively), glob patterns, files, ``.txt`` lists.

:func:`resolve_sources` turns any number of SOURCE arguments into :class:`SourceFile` s, images and videos, each
with an output name that is unique in the run and says where the file came from: a file found in a folder or by a
pattern is named by its path below that folder (``100MEDIA/DJI_0001.JPG`` -> ``100MEDIA_DJI_0001``), a file given
by itself by its stem. Extensions are matched regardless of case (``.JPG``), hidden files and folders (``.Trashes``,
macOS's ``._DJI_0001.JPG``) are left out, a folder's broken links and the sub-folders it may not read too (with a
warning naming them), and so are the pictures an earlier predict run wrote into a folder a folder or pattern reaches
(a folder marked as a run's output, :func:`~dapm_lightning.inference.run_folder.is_output_folder`), with one note
naming the folder.
"""

from __future__ import annotations

import codecs
import glob
import os
import re
import warnings
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


def permission_denied(path: Path) -> ValueError:
    """The error for a source file or folder this user may not read."""
    how = "chmod -R u+rX" if path.is_dir() else "chmod u+r"
    return ValueError(f"{path}: cannot be read (permission denied)\nFix: make it readable ({how} {path}), or leave "
                      "it out of the source")


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


def _folder_files(path: Path) -> list[Path]:
    """The files in a folder and its sub-folders, sorted; hidden ones left out, links to folders not followed.

    A sub-folder that cannot be listed, and a link to an image or video that is not there, are warned about by
    name (their images are not predicted); a folder that cannot be listed itself is refused.
    """
    unlisted: list[OSError] = []
    files: list[Path] = []
    broken: list[Path] = []
    for top, subfolders, names in os.walk(path, onerror=unlisted.append):
        subfolders[:] = [name for name in subfolders if not name.startswith(".")]
        for file in (Path(top, name) for name in names if not name.startswith(".")):
            if file.is_file():
                files.append(file)
            elif file.is_symlink() and file_kind(file):
                broken.append(file)
    for error in unlisted:
        folder = Path(error.filename)
        if folder == path:
            raise permission_denied(path) if isinstance(error, PermissionError) else error
        reason = "permission denied" if isinstance(error, PermissionError) else error.strerror
        warnings.warn(f"{folder}: this sub-folder of {path} cannot be read ({reason}): its images are not "
                      f"predicted. Fix: make it readable (chmod -R u+rX {folder}) to predict them", stacklevel=2)
    if broken:
        links = ", ".join(f"{p.relative_to(path)} -> {os.readlink(p)}" for p in broken[:3])
        warnings.warn(f"{path}: {len(broken)} broken link(s) not predicted (the file each names is not there): "
                      f"{links}{', ...' if len(broken) > 3 else ''}. Fix: put the files back where the links point, "
                      "or remove the links", stacklevel=2)
    return sorted(files)


def _folder(path: Path) -> tuple[list[tuple[Path, str]], list[str]]:
    """A folder's images, sub-folders included; notes on what it also holds.

    The videos it holds are noted, not predicted; so are the predict output folders in it (their pictures left out).
    """
    files, notes, outputs = _run_outputs(_folder_files(path))
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
    for number, line in enumerate(_list_text(path).splitlines(), 1):
        entry = line.strip()
        if entry and not entry.startswith("#"):
            target = Path(entry).expanduser()
            entries.append((number, entry, str(target if target.is_absolute() else path.parent / target)))
    return entries


def _list_text(path: Path) -> str:
    """A ``.txt`` list as text: UTF-8 (a byte-order mark allowed), or UTF-16 with its mark (Windows' "Unicode")."""
    try:
        data = path.read_bytes()
    except PermissionError:
        raise permission_denied(path) from None
    utf16 = data.startswith((codecs.BOM_UTF16_LE, codecs.BOM_UTF16_BE))
    try:
        return data.decode("utf-16" if utf16 else "utf-8-sig")
    except UnicodeDecodeError as error:
        line = error.object[:error.start].decode(error.encoding, "replace").count("\n") + 1
        raise ValueError(f"{path} line {line}: not {'UTF-16' if utf16 else 'UTF-8'} text (byte "
                         f"0x{error.object[error.start]:02x}): a list of paths is read as UTF-8 (or UTF-16 with its "
                         "byte-order mark)\nFix: save it as UTF-8 text (in an editor: Save as, encoding UTF-8), one "
                         "path a line") from None


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
