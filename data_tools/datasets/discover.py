"""Find the slides of a folder, their annotations and labels (``data_tools dataset``).

Slides: ``*.svs``, ``*.tif`` / ``*.tiff`` (pyramidal TIFF, OME-TIFF), ``*.ndpi``, ``*.qptiff``, BigTIFF
(``*.btf``, ``*.tf8``, ``*.tf2``) and DICOM WSI series (the DICOM files of a folder, ``.dcm``, named by UID or
without extension, are one slide named after the folder; other slides, annotations and sub-folders beside them are
still searched), found recursively. Only regular files are opened (a FIFO named ``x.tif`` is skipped, never
read); a folder reached twice through symlinks (a loop) is searched once. Every file passed over is listed
with why (``skipped``): formats histojax does not read (MIRAX, VSI, CZI, iSyntax, SCN, BIF ...), special
files, broken links, ``.json`` / ``.xml`` that are no annotation. A slide's name is its file name without the extension; names are matched case-insensitively (CAMELYON16 names
slides ``tumor_001.tif`` but lists ``Test_001`` in ``reference.csv``). Annotations: ASAP XML,
GeoJSON (``.geojson`` / ``.json``) and NCRF JSON (``{"positive": [...], "negative": [...]}``), in the
same tree or ``--annotations DIR``, matched to a slide by name.

CAMELYON16 as downloaded (``training/tumor/*.tif``, ``training/normal/*.tif``,
``training/lesion_annotations/*.xml``, ``testing/images/*.tif``, ``testing/reference.csv``) is
recognised: labels from the folder (training) and ``reference.csv`` (testing), split = the official
one.
"""

from __future__ import annotations

import errno
import os
import stat
from dataclasses import dataclass, field
from pathlib import Path

from data_tools.datasets.split import read_label_table, slide_key
from data_tools.errors import HistojaxDataError
from data_tools.slide_files.dicom import is_dicom

SLIDE_EXTENSIONS = (
    ".svs",
    ".tif",
    ".tiff",
    ".ndpi",
    ".qptiff",
    ".btf",
    ".tf8",
    ".tf2",
    ".mrxs",
    ".scn",
    ".bif",
    ".vms",
    ".vmu",
    ".svslide",
)
"""Slide files searched (tifffile reads TIFF, BigTIFF, OME-TIFF, Akoya QPTIFF, Hamamatsu NDPI; OpenSlide, the extra
``histojax[openslide]``, reads MIRAX, Leica SCN, Ventana BIF, Hamamatsu VMS / VMU and Sakura SVSlide)."""
ANNOTATION_EXTENSIONS = (".xml", ".geojson", ".json")
OTHER_SLIDE_FORMATS = {
    ".vsi": "Olympus VSI",
    ".czi": "Zeiss CZI",
    ".isyntax": "Philips iSyntax",
    ".kfb": "KFBio KFB",
    ".sdpc": "SQRAY SDPC",
}
"""Whole-slide formats histojax does not read: listed as skipped with the format named (convert them to
pyramidal TIFF / OME-TIFF first, e.g. with ``bfconvert`` or ``vips``)."""


@dataclass
class Skipped:
    """A file or folder the search passed over and why (``reason``, one line)."""

    path: Path
    reason: str

    def __str__(self) -> str:
        return f"{self.path}: {self.reason}"


@dataclass
class SlideEntry:
    """One slide of the cohort: ``path`` (file or DICOM folder), ``annotation`` (file or None) of kind
    ``"asap"`` / ``"geojson"`` / ``"ncrf"``, ``label`` (0/1) and where it came from, ``split``
    (``"train"`` / ``"test"`` / None = seeded)."""

    name: str
    path: Path
    annotation: Path | None = None
    annotation_kind: str | None = None
    label: int = 0
    label_source: str = "no annotation: normal"
    split: str | None = None
    extra: dict = field(default_factory=dict)


def _annotation_kind(path: Path) -> str | None:
    """``"asap"``, ``"geojson"``, ``"ncrf"`` or None (not an annotation: ignored) from the file's start."""
    try:
        with open(path, "rb") as f:
            head = f.read(4096)
    except OSError:
        return None
    if path.suffix.lower() == ".xml":
        return "asap" if b"Annotation" in head else None
    text = head.lstrip()
    if not text.startswith(b"{"):
        return None
    if path.suffix.lower() == ".geojson" or b'"type"' in head and (b"Feature" in head):
        return "geojson"
    if b'"positive"' in head or b'"negative"' in head:
        return "ncrf"
    return None


def _real(path) -> Path:
    """The real path (symlinks resolved; a symlink loop gives the path as far as it resolves, never an error)."""
    return Path(os.path.realpath(path))


def _unreadable(path: Path, e: OSError) -> str:
    if e.errno == errno.ELOOP:
        return "a symlink loop (links that lead back to each other): not followed"
    if path.is_symlink() and e.errno == errno.ENOENT:
        return "a broken link (its target does not exist)"
    return f"cannot be read ({e.strerror or e})"


def _file_kind(mode: int) -> str:
    for test, name in (
        (stat.S_ISFIFO, "a FIFO"),
        (stat.S_ISSOCK, "a socket"),
        (stat.S_ISCHR, "a character device"),
        (stat.S_ISBLK, "a block device"),
        (stat.S_ISDIR, "a folder"),
    ):
        if test(mode):
            return name
    return "not a regular file"


def _other_file_reason(name: str) -> str:
    low = name.lower()
    ext = os.path.splitext(low)[1]
    if ext in OTHER_SLIDE_FORMATS:
        return (
            f"a {OTHER_SLIDE_FORMATS[ext]} slide, a format histojax does not read (it reads SVS, TIFF / BigTIFF, "
            "OME-TIFF, QPTIFF, NDPI, DICOM WSI and, through OpenSlide, MIRAX, SCN, BIF, VMS / VMU, SVSlide); "
            "convert it to a pyramidal TIFF"
        )
    if ext == ".dcm":
        return "named .dcm but not a DICOM file"
    if ext == ".csv":
        return "a table: labels are read from --labels (or CAMELYON16's testing/reference.csv)"
    if ext == ".h5":
        return "an HDF5 file: features are read from --features-from"
    return f"not a slide ({', '.join(SLIDE_EXTENSIONS)}, DICOM) or an annotation ({', '.join(ANNOTATION_EXTENSIONS)})"


def _stat_or_skip(path: Path, skipped: list) -> os.stat_result | None:
    """``os.stat(path)`` (links followed), or None with ``path`` and why added to ``skipped``."""
    try:
        return os.stat(path)
    except OSError as e:
        skipped.append(Skipped(path, _unreadable(path, e)))
        return None


def _walk(root: Path, skip, skipped: list[Skipped]):
    """(slides, annotation files) under ``root``. A folder holding DICOM files (``.dcm``, or any other name
    but a slide's or an annotation's, as PACS exports write them) is one DICOM slide; the other slides, annotations and
    sub-folders beside them are still searched. Only regular files are looked at (a FIFO, socket or device
    is never opened); a folder reached twice (a symlink loop, or two links to one folder) and a file
    reached twice (a link beside its target) are searched once. What is passed over goes to
    ``skipped`` with why (hidden names, starting with ``.``, and the folders in ``skip`` are not listed)."""
    slides, annotations = [], []
    skip = [_real(s) for s in skip]
    seen_dirs: dict[tuple[int, int], Path] = {}
    identity: dict[Path, tuple[int, int]] = {}  # file -> (st_dev, st_ino)
    try:
        st = os.stat(root)
        seen_dirs[(st.st_dev, st.st_ino)] = root
    except OSError:
        pass
    for folder, dirs, files in os.walk(root, followlinks=True):
        here = Path(folder)
        real = _real(here)
        if any(real == s or s in real.parents for s in skip):
            dirs[:] = []
            continue
        keep = []
        mirax = {f[:-5] for f in files if f.lower().endswith(".mrxs")}  # a MIRAX slide's data folder: part of it
        for d in sorted(dirs, key=lambda d: (os.path.islink(os.path.join(folder, d)), d)):  # folders before links
            if d.startswith(".") or d in mirax:
                continue
            p = here / d
            st = _stat_or_skip(p, skipped)
            if st is None:
                continue
            key = (st.st_dev, st.st_ino)
            if key in seen_dirs:
                target = _real(p)
                if target == real or target in real.parents:
                    reason = f"a link to {target}, a folder it lies in (a symlink loop): not searched again"
                else:
                    reason = f"the same folder as {seen_dirs[key]}: searched once"
                skipped.append(Skipped(p, reason))
                continue
            seen_dirs[key] = p
            keep.append(d)
        dirs[:] = keep
        regular: dict[str, Path] = {}
        for f in sorted(files):
            if f.startswith("."):
                continue
            p = here / f
            st = _stat_or_skip(p, skipped)
            if st is None:
                continue
            if not stat.S_ISREG(st.st_mode):
                skipped.append(Skipped(p, f"{_file_kind(st.st_mode)}, not a regular file: never opened"))
                continue
            identity[p] = (st.st_dev, st.st_ino)
            regular[f] = p
        known = SLIDE_EXTENSIONS + ANNOTATION_EXTENSIONS + (".csv", ".h5")
        dicom = {
            f
            for f, p in regular.items()  # .dcm, no extension, or a UID as the name (1.2.840.....)
            if (f.lower().endswith(".dcm") or not f.lower().endswith(known)) and is_dicom(p)
        }
        if dicom:
            slides.append(here)
        in_bundle = (here / "metadata.json").is_file()  # a bundle's own files are not the user's slides
        for f, p in regular.items():
            low = f.lower()
            if f in dicom:
                continue
            if low.endswith(SLIDE_EXTENSIONS):
                slides.append(p)
            elif low.endswith(ANNOTATION_EXTENSIONS):
                annotations.append(p)
            elif not in_bundle:
                skipped.append(Skipped(p, _other_file_reason(f)))
    chosen: dict[tuple[int, int], Path] = {}  # one path per file reached twice: the file itself before a link
    for p, key in identity.items():
        if key not in chosen or (chosen[key].is_symlink() and not p.is_symlink()):
            chosen[key] = p

    def once(paths):
        keep = []
        for p in paths:
            first = chosen.get(identity.get(p), p)
            if first == p:
                keep.append(p)
            else:
                skipped.append(Skipped(p, f"the same file as {first}: used once"))
        return keep

    return once(slides), once(annotations)


def by_name(
    paths, what: str, hint: str = "names identify slides, rename one or build the folders separately"
) -> dict[str, Path]:
    """Paths keyed by lower-cased slide name; two files of one name in two folders are an error naming both,
    then ``hint``."""
    out: dict[str, Path] = {}
    for p in paths:
        key = slide_key(p.name).lower()
        if key in out:
            raise HistojaxDataError(p, f"two {what} named {slide_key(p.name)!r}: {out[key]} and {p}; {hint}")
        out[key] = p
    return out


def camelyon16_layout(root: Path) -> bool:
    """Whether ``root`` looks like CAMELYON16 as downloaded (``training/tumor``, ``training/normal`` or
    ``testing/images``)."""
    return any((root / p).is_dir() for p in ("training/tumor", "training/normal", "testing/images"))


def discover(
    root,
    annotations_dir=None,
    labels_csv=None,
    skip=(),
    allow_unmatched: bool = False,
    skipped: list | None = None,
    warn_skipped: bool = True,
) -> list[SlideEntry]:
    """The cohort under ``root`` (see the module doc), sorted by name. Errors (one line, naming the
    file): no slides; two slides or annotations of one name; an annotation naming no slide (unless
    ``allow_unmatched``); a label table naming unknown slides or missing some; CAMELYON16 testing
    slides without ``testing/reference.csv``. ``skipped``: a list that receives a :class:`Skipped`
    (path, why) for every file or folder passed over (other formats, FIFOs, broken links, symlink
    loops, ``.json`` / ``.xml`` that are no annotation); each is also a warning (``warn_skipped``), which
    the CLI prints as one ``warning:`` line."""
    root = Path(root)
    skipped = [] if skipped is None else skipped
    if not root.is_dir():  # a file is not a folder of slides: say which it is
        raise HistojaxDataError(
            root,
            "a file, not a folder of slides (give the folder that holds them)"
            if root.exists()
            else "no such folder of slides",
        )
    slide_paths, ann_paths = _walk(root, list(skip), skipped)
    if annotations_dir is not None:
        if not Path(annotations_dir).is_dir():
            raise HistojaxDataError(annotations_dir, "no such folder of annotations")
        _, more = _walk(Path(annotations_dir), list(skip), skipped)
        ann_paths += more
    kinds = {p: _annotation_kind(p) for p in ann_paths}
    skipped += [
        Skipped(p, f"a {p.suffix} file that is not an ASAP XML, GeoJSON or NCRF JSON annotation")
        for p, k in kinds.items()
        if not k
    ]
    ann_paths = [p for p in ann_paths if kinds[p]]
    used = {_real(labels_csv)} if labels_csv is not None else set()  # tables read: not skipped
    c16 = camelyon16_layout(root)
    skipped[:] = [
        item
        for item in skipped
        if _real(item.path) not in used and not (c16 and item.path.name.lower() == "reference.csv")
    ]
    if warn_skipped:
        import warnings

        for item in skipped:  # the CLI prints each as one `warning:` line
            warnings.warn(f"{item.path}: skipped: {item.reason}", stacklevel=2)
    if not slide_paths:
        raise HistojaxDataError(root, f"holds no slides ({', '.join(SLIDE_EXTENSIONS)} files or DICOM folders)")
    slides = by_name(slide_paths, "slides")
    anns = by_name(ann_paths, "annotation files")
    orphans = sorted(set(anns) - set(slides))
    if orphans and not allow_unmatched:
        raise HistojaxDataError(
            anns[orphans[0]],
            f"annotation for a slide that is not in {root} ({len(orphans)} "
            f"such: {', '.join(anns[k].name for k in orphans[:4])}"
            f"{', ...' if len(orphans) > 4 else ''}); a misspelt name would make a tumour "
            "slide look normal. Pass --allow-unmatched-annotations if only part of the "
            "cohort is here",
        )
    entries = []
    for key, path in sorted(slides.items()):
        e = SlideEntry(name=slide_key(path.name), path=path)
        if key in anns:
            e.annotation, e.annotation_kind = anns[key], _annotation_kind(anns[key])
            e.label, e.label_source = 1, f"annotated ({anns[key].name}): tumour"
        entries.append(e)
    if c16:
        _camelyon16_labels(root, entries)
    if labels_csv is not None:
        _table_labels(Path(labels_csv), entries)
    return sorted(entries, key=lambda e: e.name)


def _camelyon16_labels(root: Path, entries: list[SlideEntry]) -> None:
    """Labels and split of CAMELYON16 as downloaded: training/tumor → 1, training/normal → 0, train;
    testing/images → test, labels from testing/reference.csv (``Test_001,Tumor,Macro,Primary``)."""
    testing = [e for e in entries if "testing" in e.path.relative_to(root).parts]
    reference = None
    if testing:
        found = sorted(root.rglob("reference.csv"))
        if not found:
            raise HistojaxDataError(
                root / "testing" / "reference.csv",
                f"missing: the labels of the {len(testing)} CAMELYON16 testing slides come from it",
            )
        reference = {k.lower(): v for k, v in read_label_table(found[0])[0].items()}
    for e in entries:
        parts = [p.lower() for p in e.path.relative_to(root).parts[:-1]]
        if "training" in parts and ("tumor" in parts or "normal" in parts):
            e.split = "train"
            e.label = int("tumor" in parts)
            e.label_source = f"CAMELYON16 folder training/{'tumor' if e.label else 'normal'}"
        elif "testing" in parts:
            e.split = "test"
            if e.name.lower() not in reference:
                raise HistojaxDataError(found[0], f"has no row for the testing slide {e.name}")
            e.label = reference[e.name.lower()]
            e.label_source = f"CAMELYON16 {found[0].name}"
        else:
            raise HistojaxDataError(
                e.path,
                "not in training/tumor, training/normal or testing/images of the "
                "CAMELYON16 layout; its label would be a guess",
            )


def _table_labels(path: Path, entries: list[SlideEntry]) -> None:
    """Labels (and split, if the table has one) from ``--labels``: every slide needs a row, every row a slide."""
    labels, splits = read_label_table(path)
    labels = {k.lower(): v for k, v in labels.items()}
    splits = {k.lower(): v for k, v in splits.items()}
    names = {e.name.lower() for e in entries}
    unknown = sorted(set(labels) - names)
    if unknown:
        raise HistojaxDataError(
            path,
            f"names {len(unknown)} slide(s) that are not in the folder: "
            f"{', '.join(unknown[:4])}{', ...' if len(unknown) > 4 else ''}",
        )
    missing = sorted(e.name for e in entries if e.name.lower() not in labels)
    if missing:
        raise HistojaxDataError(
            path,
            f"has no label for {len(missing)} slide(s): {', '.join(missing[:4])}{', ...' if len(missing) > 4 else ''}",
        )
    for e in entries:
        new = labels[e.name.lower()]
        if e.split is not None and e.label != new:  # a layout label (CAMELYON16 folder) disagrees
            raise HistojaxDataError(path, f"labels {e.name} {new} but {e.label_source} says {e.label}")
        e.label, e.label_source = new, f"label table {path.name}"
        if splits:
            e.split = splits[e.name.lower()]


def ncrf_to_geojson(path: Path, out: Path) -> Path:
    """Write the NCRF JSON ``path`` as GeoJSON ``out`` (``positive`` → tumour, ``negative`` → exclusion on
    tumour slides; on slides without ``positive`` polygons, ``negative`` is tissue), atomically."""
    from shapely.geometry import mapping

    from data_tools.bundle_files.writes import write_json
    from data_tools.ncrf import parse_ncrf

    s = parse_ncrf(slide_key(path.name), path.read_bytes(), path)
    pairs = [("tumour", s.positive), ("exclusion", s.negative)] if not s.positive.is_empty else [("tissue", s.negative)]
    doc = {
        "type": "FeatureCollection",
        "features": [
            {"type": "Feature", "properties": {"label": label, "source": path.name}, "geometry": mapping(g)}
            for label, g in pairs
            if not g.is_empty
        ],
    }
    out.parent.mkdir(parents=True, exist_ok=True)
    write_json(out, doc)
    return out


__all__ = [
    "ANNOTATION_EXTENSIONS",
    "OTHER_SLIDE_FORMATS",
    "SLIDE_EXTENSIONS",
    "SlideEntry",
    "Skipped",
    "camelyon16_layout",
    "discover",
    "ncrf_to_geojson",
]
