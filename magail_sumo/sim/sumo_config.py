"""SUMO started only with options the tool chose, never with a configuration file as written.

A SUMO configuration (``.sumocfg``, ``run.sumo.cfg``, ...) is a list of command-line options,
and SUMO honours every one of them: ``<tripinfo-output value="/elsewhere/x"/>`` replaces a
file outside any output folder, ``<log>`` creates one, ``<remote-port>`` opens a TraCI server
on every interface. So the tool never passes a configuration to SUMO (no ``-c``): it reads the
file here, as SUMO's own option loader does, and builds the command line itself
(:class:`SumoInputs`, :meth:`SumoInputs.args`):

* **Reading** (:func:`read_config`): every element with a ``value`` (or ``v``) attribute, at any
  depth, sets the option its tag names (section elements such as ``<input>`` are ignored, so
  flat and sectioned layouts read alike); synonyms (``net``, ``n``) map to the option's name;
  file lists split at commas; relative names are relative to the configuration's folder.
* **Inputs** (the ``FILE`` options of SUMO's ``input`` section: ``net-file``,
  ``route-files``, ``additional-files``, ``weight-files``, ``load-state``): each resolved and
  checked to be an existing regular file (:func:`magail_sumo.inputs.regular_file`: no FIFO,
  device or socket, also through a link); a missing one is one line naming the configuration
  and the file, as SUMO words it.
* **Behaviour options** (time, processing, routing, mesoscopic, emissions, the vehicle
  devices' settings, ``seed``) are kept as the file gives them.
* **Dropped**, listed in :attr:`SumoInputs.dropped`: every output, report and log option,
  TraCI's ``remote-port`` and every other ``communication`` / ``traci_server`` option, the
  GUI's options, configuration saving, ``random`` (the tool seeds SUMO itself), the ``ssm``,
  ``toc`` and ``fcd-replay`` devices (they write or read files of their own), every other
  ``FILE`` option outside ``input``, and options the installed SUMO does not know.
* **Files SUMO reads that write** (:func:`check_demand`, :func:`clean_additional`): an
  additional file may declare outputs (``<edgeData file=...>``, detectors, probes,
  ``<calibrator output=...>``, ``<timedEvent dest=...>``; a file name ``host:port`` even makes
  SUMO connect out) and may include other files. Such a file is passed as a cleaned copy (in
  the session's private folder) whose outputs go to ``NUL`` (SUMO's null device: nothing is
  written) and whose references are made absolute; each output so silenced is listed in
  :attr:`SumoInputs.dropped`. A ``<param>`` that equips vehicles with a device writing its own
  files (``has.ssm.device``, ``has.toc.device``, ``device.<name>.file`` / ``.output``), in a
  route or an additional file, is refused in one line naming file, element and key.

The option table (:data:`OPTIONS`: section, type, synonyms of every option of the installed
``sumo``) ships as ``sumo_options.json``, generated from ``sumo --save-template`` by
:func:`template_table` (``tests/test_sumo_config.py`` compares it with the installed SUMO;
``python -m magail_sumo.sim.sumo_config`` writes it anew after a SUMO upgrade).
"""

from __future__ import annotations

import gzip
import zlib
import io
import json
import re
import subprocess
import tempfile
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from functools import lru_cache
from os import PathLike
from pathlib import Path

from magail_sumo.errors import MagailSumoError
from magail_sumo.inputs import GiB, MiB, InputFileError, open_regular, read_bytes, regular_file
from magail_sumo.sim.binaries import binary


class SumoConfigError(MagailSumoError):
    """A SUMO configuration or a file it names cannot be used; one line naming the file."""


#: sections whose options are all dropped (outputs, logs, ports, GUI, configuration saving)
DROPPED_SECTIONS = frozenset({"output", "report", "communication", "traci_server",
                              "configuration", "gui_only", "ssm_device", "toc_device",
                              "fcd_replay_device"})
#: single options dropped from kept sections: the tool seeds SUMO itself
DROPPED_OPTIONS = frozenset({"random"})
#: a kept-section option whose name says it writes a file
_WRITES = re.compile(r"(^|[.-])(output|file)$")
#: a ``<param key=...>`` equipping vehicles with a device that writes files of its own
DEVICE_PARAM = re.compile(r"^(has\.(ssm|toc)\.device|device\.[^.]+\.(file|output))$")
#: elements whose ``file`` attribute SUMO reads (all other ``file`` attributes are outputs)
_READS_FILE = frozenset({"variableSpeedSign", "vss", "rerouter"})
#: attributes of additional-file elements that name a file SUMO reads
_INPUT_ATTRS = ("href", "imgFile")
#: where a silenced output goes: SUMO's null device (nothing is written)
NULL_OUTPUT = "NUL"
#: ``<tlLogic>`` parameters naming a file SUMO writes (actuated / delay-based detectors)
TLS_OUTPUTS = frozenset({"file", "output"})
#: caps on what is read here: a configuration, one additional file (per include)
CONFIG_LIMIT = 16 * MiB
ADDITIONAL_LIMIT = 1 * GiB
#: include depth of additional files
MAX_INCLUDE_DEPTH = 8
#: the most files one input may pull in through includes (all levels): a few kilobytes of
#: files including each other several times per level would otherwise be read millions of
#: times (an include bomb)
MAX_INCLUDED_FILES = 512
#: the most a streamed SUMO input (routes, a saved state, a network) may unpack to: a city's
#: demand is hundreds of MB; a gzip bomb is refused at this point, not read to the end
STREAM_LIMIT = 4 * GiB


class _Includes:
    """The include budget of one input file's scan (:data:`MAX_INCLUDED_FILES`)."""

    def __init__(self, top: Path) -> None:
        self.top, self.left = top, MAX_INCLUDED_FILES

    def take(self, path: Path) -> None:
        self.left -= 1
        if self.left < 0:
            raise SumoConfigError(f"{self.top}: includes more than {MAX_INCLUDED_FILES} files "
                                  f"(counting repeats; the last: {path})")


class _Capped:
    """A binary stream that refuses to yield more than ``limit`` bytes."""

    def __init__(self, fh, limit: int, path: Path) -> None:
        self.fh, self.left, self.path, self.limit = fh, limit, path, limit

    def read(self, n: int = -1) -> bytes:
        data = self.fh.read(n if n is not None and n >= 0 else self.left + 1)
        self.left -= len(data)
        if self.left < 0:
            raise SumoConfigError(f"{self.path}: unpacks to more than "
                                  f"{self.limit >> 30} GiB")
        return data
#: the shipped option table (module doc)
OPTIONS_FILE = Path(__file__).with_name("sumo_options.json")


#: file names SUMO scenario configurations go by (``run.sumo.cfg`` included)
CONFIG_SUFFIXES = (".sumocfg", ".sumo.cfg")
_CONFIG_ROOT = re.compile(rb"<\s*(configuration|sumoConfiguration)[\s>/]")


def is_sumo_config(path: str | PathLike) -> bool:
    """Whether ``path`` is a SUMO scenario configuration: named ``*.sumocfg`` / ``*.sumo.cfg``,
    or an XML file (gzipped or not) whose root element is ``configuration`` /
    ``sumoConfiguration`` (its first 4 KiB after the XML declaration and comments); a
    directory, a missing path or a FIFO / device is not."""
    p = Path(path)
    try:
        regular_file(p)
    except InputFileError:
        return False
    if p.name.lower().endswith(CONFIG_SUFFIXES):
        return True
    try:
        with open_regular(p) as fh:
            head = fh.read(4096)
        if head[:2] == b"\x1f\x8b":
            head = gzip.GzipFile(fileobj=io.BytesIO(read_bytes(p, CONFIG_LIMIT))).read(4096)
    except (InputFileError, OSError, EOFError, zlib.error):
        return False
    head = re.sub(rb"<\?.*?\?>|<!--.*?-->", b"", head, flags=re.S).lstrip()
    return bool(_CONFIG_ROOT.match(head))


#: configuration names that say nothing of the scenario: its folder names it instead
GENERIC_NAMES = frozenset({"osm", "run", "config", "configuration", "scenario", "simulation",
                           "sim", "sumo", "main", "default"})


def scenario_name(config: str | PathLike) -> str:
    """A city scenario's name: its configuration's file name without ``.sumocfg`` /
    ``.sumo.cfg`` / ``.cfg`` / ``.xml`` (``cologne8.sumocfg`` -> ``cologne8``), or its folder's
    name when that says nothing (``port_cologne/osm.sumocfg`` -> ``port_cologne``,
    ``monaco/run.sumo.cfg`` -> ``monaco``)."""
    p = Path(config)
    name = p.name
    for suffix in (*CONFIG_SUFFIXES, ".cfg", ".xml", ".gz"):
        if name.lower().endswith(suffix):
            name = name[:-len(suffix)]
    if name.lower() in GENERIC_NAMES or not name:
        return p.absolute().parent.name or name
    return name


def config_of(path: str | PathLike) -> Path | None:
    """The SUMO configuration ``path`` names: the file itself when :func:`is_sumo_config`, or
    the one a scenario folder holds (:func:`find_config`); None otherwise."""
    p = Path(path)
    return find_config(p) if p.is_dir() else (p if is_sumo_config(p) else None)


def find_config(folder: str | PathLike) -> Path | None:
    """The SUMO configuration a scenario folder holds: the one file directly in it that
    :func:`is_sumo_config` names by its name (else by its content); None when it holds none;
    :class:`SumoConfigError` naming them when it holds several."""
    d = Path(folder)
    if not d.is_dir():
        return None
    files = sorted(f for f in d.iterdir() if f.is_file())
    named = [f for f in files if f.name.lower().endswith(CONFIG_SUFFIXES)]
    found = named or [f for f in files if f.suffix.lower() in (".cfg", ".xml")
                      and is_sumo_config(f)]
    if len(found) > 1:
        raise SumoConfigError(f"{d}: holds {len(found)} SUMO configurations "
                              f"({', '.join(f.name for f in found[:5])}); name one")
    return found[0] if found else None


@dataclass(frozen=True)
class SumoOption:
    """One option of the installed ``sumo``: its section in ``--save-template``, its type
    (``FILE``, ``BOOL``, ``STR[]``, ...) and its synonyms."""

    name: str
    section: str
    type: str
    synonyms: tuple[str, ...] = ()

    @property
    def kept(self) -> bool:
        """Whether a configuration may set it (module doc)."""
        if self.section in DROPPED_SECTIONS or self.name in DROPPED_OPTIONS:
            return False
        if self.section == "input":
            return True
        return self.type != "FILE" and not _WRITES.search(self.name)

    @property
    def is_input_file(self) -> bool:
        return self.section == "input" and self.type == "FILE"


_TEMPLATE_ROW = re.compile(r"^\s*<([^\s>/!]+) (.*?)/>\s*$")
_ATTR = re.compile(r'([\w.-]+)="([^"]*)"')
_SECTION_ROW = re.compile(r"^    <([A-Za-z_]+)>\s*$")


def template_table(template: str) -> dict[str, dict]:
    """The option table of a ``sumo --save-template FILE`` text: ``{name: {"section",
    "type", "synonyms"}}`` (parsed by line: the template is not always well-formed XML)."""
    table: dict[str, dict] = {}
    section = ""
    for line in template.splitlines():
        if m := _SECTION_ROW.match(line):
            section = m.group(1)
        elif (m := _TEMPLATE_ROW.match(line)) and "type" in (attrs := dict(
                _ATTR.findall(m.group(2)))):
            table[m.group(1)] = {"section": section, "type": attrs["type"],
                                 "synonyms": attrs.get("synonymes", "").split()}
    return table


@lru_cache(maxsize=1)
def _options() -> tuple[dict[str, SumoOption], dict[str, str]]:
    raw = json.loads(OPTIONS_FILE.read_text())
    options = {name: SumoOption(name, o["section"], o["type"], tuple(o["synonyms"]))
               for name, o in raw["options"].items()}
    alias = {s: name for name, o in options.items() for s in (name, *o.synonyms)}
    return options, alias


def option(name: str) -> SumoOption | None:
    """The option ``name`` names (its own name or a synonym); None when SUMO has none."""
    options, alias = _options()
    canonical = alias.get(name.lstrip("-"))
    return None if canonical is None else options[canonical]


@dataclass(frozen=True)
class SumoInputs:
    """What SUMO is started with (module doc).

    :param source: the configuration the inputs came from (messages), or None.
    :param files: ``{option: (absolute paths...)}`` of the input files, checked.
    :param options: ``((option, value), ...)`` behaviour options kept from the configuration.
    :param dropped: human-readable notes of what the configuration asked for and the tool did
        not pass (``"tripinfo-output (output)"``, ``"a.add.xml: edgeData 'x' file"``).
    :param cleaned: ``((original, text), ...)``: additional files to pass as cleaned copies,
        in :meth:`args` order (written by :meth:`materialise`).
    """

    source: Path | None
    files: dict[str, tuple[Path, ...]]
    options: tuple[tuple[str, str], ...] = ()
    dropped: tuple[str, ...] = ()
    cleaned: tuple[tuple[Path, bytes], ...] = field(default=(), repr=False)

    @property
    def net(self) -> Path:
        return self.files["net-file"][0]

    @property
    def routes(self) -> tuple[Path, ...]:
        return self.files.get("route-files", ())

    @property
    def additional(self) -> tuple[Path, ...]:
        return self.files.get("additional-files", ())

    def option(self, name: str) -> str | None:
        """The configuration's value of option ``name`` (kept ones only), else None."""
        return dict(self.options).get(name)

    def materialise(self, folder: str | PathLike) -> dict[Path, Path]:
        """Write the cleaned additional files into ``folder`` (private to one session);
        returns ``{original: copy}``."""
        out = {}
        for k, (original, text) in enumerate(self.cleaned):
            copy = Path(folder) / f"{k:03d}_{original.name.removesuffix('.gz')}"
            copy.write_bytes(text)
            out[original] = copy
        return out

    def args(self, overrides: dict[str, str] | None = None,
             copies: dict[Path, Path] | None = None) -> list[str]:
        """SUMO command-line options (after the binary's name): input files, then behaviour
        options, ``overrides`` (option name -> value) replacing the configuration's values of
        the same options; additional files replaced by their ``copies``."""
        copies = copies or {}
        args: list[str] = []
        for name, paths in self.files.items():
            args += [f"--{name}", ",".join(str(copies.get(p, p)) for p in paths)]
        over = {option(k).name if option(k) else k: v for k, v in (overrides or {}).items()}
        for name, value in self.options:
            if name not in over:
                args += [f"--{name}", value]
        for name, value in over.items():
            args += [f"--{name}", value]
        return args


def _resolve(cfg: Path, name: str, value: str) -> tuple[Path, ...]:
    paths = []
    for item in (v.strip() for v in value.split(",")):
        if not item:
            continue
        path = Path(item) if Path(item).is_absolute() else cfg.parent / item
        try:
            regular_file(path, "a file")
        except InputFileError as exc:
            problem = "not found" if exc.problem == "no such file" else exc.problem
            raise SumoConfigError(f"{cfg}: {name} {item}: {problem}") from None
        paths.append(Path(path).absolute())
    return tuple(paths)


_DOCTYPE = re.compile(rb"<!(DOCTYPE|ENTITY)", re.I)


def _no_doctype(head: bytes, path: Path) -> None:
    """Refuse a document type declaration: SUMO's XML parser resolves its entities (an external
    entity pulls in content no check saw) and no SUMO file needs one."""
    if _DOCTYPE.search(head):
        raise SumoConfigError(f"{path}: declares a DOCTYPE / ENTITY (SUMO would expand entities "
                              "the tool cannot check); SUMO files need none")


def _open_xml(path: Path, limit: int) -> io.BytesIO:
    """The bytes of XML file ``path`` (gzipped or not) as a stream, at most ``limit``; a
    DOCTYPE / ENTITY declaration is refused."""
    data = read_bytes(path, limit, "a SUMO XML file")
    if data[:2] == b"\x1f\x8b":
        try:
            with gzip.GzipFile(fileobj=io.BytesIO(data)) as gz:
                data = gz.read(limit + 1)
        except (OSError, EOFError, zlib.error) as exc:
            raise SumoConfigError(f"{path}: not a readable gzip file ({exc})") from None
        if len(data) > limit:
            raise SumoConfigError(f"{path}: unpacks to more than {limit >> 20} MiB")
    _no_doctype(data, path)
    return io.BytesIO(data)


def read_config(path: str | PathLike, *, allowed: set[str] | None = None) -> SumoInputs:
    """The :class:`SumoInputs` of SUMO configuration ``path`` (module doc).

    :param allowed: when given, the only input file names (folder included, resolved) the
        configuration may name, e.g. a converted bundle's own files.
    :raises SumoConfigError: not readable, not XML, no net file, or an input file missing or
        not a regular file, or a device-writing ``<param>`` (one line naming the file).
    """
    cfg = Path(path)
    try:
        stream = _open_xml(cfg, CONFIG_LIMIT)
        root = ET.parse(stream).getroot()
    except InputFileError as exc:
        problem = "SUMO config file not found" if exc.problem == "no such file" else exc.problem
        raise SumoConfigError(f"{cfg}: {problem}") from None
    except ET.ParseError as exc:
        raise SumoConfigError(f"{cfg}: not valid XML ({exc})") from None
    files: dict[str, tuple[Path, ...]] = {}
    options: dict[str, str] = {}
    dropped: list[str] = []
    for el in root.iter():
        value = el.get("value", el.get("v"))
        if value is None or el is root:
            continue
        opt = option(el.tag)
        if opt is None:
            dropped.append(f"{el.tag} (not an option of this SUMO)")
        elif not opt.kept:
            dropped.append(f"{opt.name} ({opt.section})")
        elif opt.is_input_file:
            files[opt.name] = _resolve(cfg, opt.name, value)
        else:
            options[opt.name] = value
    if not files.get("net-file"):
        raise SumoConfigError(f"{cfg}: names no net-file (SUMO needs a network)")
    if allowed is not None:
        for paths in files.values():
            for p in paths:
                if str(p.resolve()) not in allowed:
                    raise SumoConfigError(f"{cfg}: names {p}, which is not one of its "
                                          "bundle's own files")
    check_network(files["net-file"][0])
    check_demand([*files.get("route-files", ()), *files.get("load-state", ())])
    for weights in files.get("weight-files", ()):  # read by SUMO: its includes too
        check_xml(weights)
    cleaned: list[tuple[Path, bytes]] = []
    for add in files.get("additional-files", ()):
        _clean(add, cleaned, dropped, depth=0, budget=_Includes(add))
    return SumoInputs(cfg.absolute(), files, tuple(options.items()), tuple(dropped),
                      tuple(cleaned))


def _check_param(path: Path, el: ET.Element, parent: str) -> None:
    key = el.get("key", "")
    if DEVICE_PARAM.match(key):
        raise SumoConfigError(f"{path}: {parent} param {key!r} equips vehicles with a SUMO "
                              "device that writes files of its own; remove it (SUMO outputs "
                              "are asked of magail-sumo, which writes them in its output folder)")


def _clean(path: Path, cleaned: list, dropped: list[str], depth: int,
           budget: _Includes) -> bool:
    """Check additional file ``path``; when it declares outputs or includes a file that does,
    append its cleaned text to ``cleaned`` (module doc). Returns whether it was cleaned. A
    file an element reads (a variable speed sign's or rerouter's ``file``) is checked with its
    includes (:func:`check_xml`)."""
    if depth > MAX_INCLUDE_DEPTH:
        raise SumoConfigError(f"{path}: includes nested deeper than {MAX_INCLUDE_DEPTH}")
    if depth:
        budget.take(path)
    try:
        tree = ET.parse(_open_xml(path, ADDITIONAL_LIMIT))
    except InputFileError as exc:
        raise SumoConfigError(str(exc)) from None
    except ET.ParseError as exc:
        raise SumoConfigError(f"{path}: not valid XML ({exc})") from None
    changed = False
    parents = {c: p for p in tree.iter() for c in p}
    for el in tree.iter():
        tag = el.tag
        if tag == "param":
            parent = parents.get(el)
            if parent is not None and parent.tag == "tlLogic" and el.get("key") in TLS_OUTPUTS:
                # actuated / delay-based programs write detector output to this file
                dropped.append(f"{path.name}: tlLogic {parent.get('id', '')!r} param "
                               f"{el.get('key')}={el.get('value')}")
                el.set("value", NULL_OUTPUT)
                changed = True
                continue
            _check_param(path, el, f"{parent.tag} {parent.get('id', '')!r}" if parent is not None
                         else "top-level")
            continue
        for attr in ("file", "output", "dest"):
            value = el.get(attr)
            if value is None or (attr == "file" and tag in _READS_FILE) or \
                    (attr == "dest" and tag != "timedEvent") or value == NULL_OUTPUT:
                continue
            el.set(attr, NULL_OUTPUT)
            dropped.append(f"{path.name}: {tag} {el.get('id', '')!r} {attr}={value}")
            changed = True
        for attr in (*_INPUT_ATTRS, *(("file",) if tag in _READS_FILE else ())):
            value = el.get(attr)
            if not value:
                continue
            ref = Path(value) if Path(value).is_absolute() else path.parent / value
            if attr == "imgFile":  # the GUI's decoration: made absolute, not required
                el.set(attr, str(ref.absolute()))
                changed = changed or ref != Path(value)
                continue
            try:
                regular_file(ref, "a file")
            except InputFileError as exc:
                raise SumoConfigError(f"{path}: {tag} {attr} {value}: {exc.problem}") from None
            target = ref.absolute()
            if tag == "include" and _clean(target, cleaned, dropped, depth + 1, budget):
                target = Path(f"{len(cleaned) - 1:03d}_{target.name.removesuffix('.gz')}")
            elif attr == "file":
                check_xml(target)
            el.set(attr, str(target))
            changed = True
    if changed:
        root = tree.getroot()
        for attr in list(root.attrib):  # schema location: its namespace prefix would change
            if attr.startswith("{"):
                del root.attrib[attr]
        cleaned.append((path, ET.tostring(root, encoding="utf-8", xml_declaration=True)))
    return changed


def _scan(path: Path, on_end, depth: int = 0, seen: tuple[Path, ...] = (),
          budget: _Includes | None = None) -> None:
    """Stream XML file ``path`` (gzipped or not) calling ``on_end(element, parent)`` for every
    element, following ``<include href>`` (relative to the including file, at most
    :data:`MAX_INCLUDE_DEPTH` deep, no loops, at most :data:`MAX_INCLUDED_FILES` files in
    all); a DOCTYPE / ENTITY declaration is refused."""
    if depth > MAX_INCLUDE_DEPTH:
        raise SumoConfigError(f"{path}: includes nested deeper than {MAX_INCLUDE_DEPTH}")
    if budget is None:
        budget = _Includes(path)
    else:
        budget.take(path)
    real = path.resolve()
    if real in seen:
        raise SumoConfigError(f"{path}: includes itself (an include loop)")
    try:
        with open_regular(path, expected="a SUMO XML file") as raw:
            head = raw.read(2)
            raw.seek(0)
            fh = gzip.GzipFile(fileobj=raw) if head == b"\x1f\x8b" else raw
            _no_doctype(fh.read(65536), path)
            fh.seek(0)
            stack: list[ET.Element] = []
            for event, el in ET.iterparse(_Capped(fh, STREAM_LIMIT, path),
                                          events=("start", "end")):
                if event == "start":
                    stack.append(el)
                    continue
                stack.pop()
                if el.tag == "include" and el.get("href"):
                    href = Path(el.get("href"))
                    ref = href if href.is_absolute() else path.parent / href
                    try:
                        regular_file(ref, "a file")
                    except InputFileError as exc:
                        raise SumoConfigError(f"{path}: include {href}: {exc.problem}") from None
                    _scan(ref, on_end, depth + 1, (*seen, real), budget)
                on_end(el, stack[-1] if stack else None, path)
                if len(stack) <= 1:
                    el.clear()
    except InputFileError as exc:
        raise SumoConfigError(str(exc)) from None
    except (OSError, EOFError, zlib.error, ET.ParseError) as exc:
        raise SumoConfigError(f"{path}: cannot read ({exc})") from None


def check_xml(path: Path) -> None:
    """Refuse an XML input SUMO reads whose includes are not regular files, nest too deep,
    loop or are too many, or that declares a DOCTYPE (read as :func:`_scan` does)."""
    _check_xml(*_stamp(Path(path)))


@lru_cache(maxsize=64)
def _check_xml(path: str, size: int, mtime_ns: int) -> None:
    _scan(Path(path), lambda *_: None)


def _where(parent: ET.Element | None) -> str:
    return f"{parent.tag} {parent.get('id', '')!r}" if parent is not None else "top-level"


def check_demand(routes: tuple[Path, ...] | list[Path]) -> list[str]:
    """Ids of the vehicles, trips and flows of route files ``routes`` (gzipped or not,
    includes followed), after refusing any device-writing ``<param>`` and any DOCTYPE (module
    doc); one pass per file. Also for saved states (``load-state``: their vehicles and
    types)."""
    ids: list[str] = []
    for path in routes:
        ids += _demand(*_stamp(Path(path)))[0]
    return ids


def _stamp(path: Path) -> tuple[str, int, int]:
    """(path, size, mtime) of a file: a cache key that changes when the file does."""
    st = path.stat()
    return str(path.absolute()), st.st_size, st.st_mtime_ns


@lru_cache(maxsize=64)
def _demand(path: str, size: int, mtime_ns: int) -> tuple[tuple[str, ...], dict[str, str]]:
    """One pass over a demand file: the ids of its vehicles, trips and flows, and its vehicle
    types' classes (:func:`vtype_classes`); device-writing params refused."""
    ids: list[str] = []
    vtypes: dict[str, str] = {}

    def on_end(el: ET.Element, parent: ET.Element | None, where: Path) -> None:
        if el.tag == "param":
            _check_param(where, el, _where(parent))
        elif el.tag in ("vehicle", "trip", "flow") and el.get("id"):
            ids.append(el.get("id"))
        elif el.tag == "vType" and el.get("id"):
            vtypes[el.get("id")] = el.get("vClass", "passenger")

    _scan(Path(path), on_end)
    return tuple(ids), vtypes


#: SUMO's built-in vehicle types and their classes
DEFAULT_VTYPES = {"DEFAULT_VEHTYPE": "passenger", "DEFAULT_PEDTYPE": "pedestrian",
                  "DEFAULT_BIKETYPE": "bicycle", "DEFAULT_TAXITYPE": "taxi",
                  "DEFAULT_RAILTYPE": "rail", "DEFAULT_CONTAINERTYPE": "ignoring"}


def vtype_classes(files: tuple[Path, ...] | list[Path]) -> dict[str, str]:
    """Vehicle type id -> SUMO vehicle class (``vClass``; ``passenger`` when a type names
    none, as SUMO defaults) of the ``<vType>`` elements of route / additional files
    ``files`` (includes followed; read in the pass :func:`check_demand` makes), SUMO's
    built-in types included."""
    out = dict(DEFAULT_VTYPES)
    for path in files:
        out.update(_demand(*_stamp(Path(path)))[1])
    return out


def check_network(path: Path) -> None:
    """Refuse a network whose traffic-light programs write files (``<tlLogic>`` ``<param
    key="file">`` of actuated / delay-based programs: SUMO writes detector output there) or
    that declares a DOCTYPE; a network is not rewritten (it can be large), so such a parameter
    is one line naming the file, program and value."""
    _check_network(*_stamp(Path(path)))


@lru_cache(maxsize=64)
def _check_network(path: str, size: int, mtime_ns: int) -> None:

    def on_end(el: ET.Element, parent: ET.Element | None, where: Path) -> None:
        if el.tag == "param" and parent is not None and parent.tag == "tlLogic" and \
                el.get("key") in TLS_OUTPUTS:
            raise SumoConfigError(
                f"{where}: tlLogic {parent.get('id', '')!r} param {el.get('key')}="
                f"{el.get('value')}: SUMO would write detector output there; remove the "
                "parameter (outputs are asked of magail-sumo, which writes them in its folder)")

    _scan(Path(path), on_end)


def write_table(path: Path = OPTIONS_FILE) -> int:
    """Write the installed ``sumo``'s option table to ``path``; returns its number of options."""
    with tempfile.TemporaryDirectory() as tmp:
        template = Path(tmp) / "template.xml"
        subprocess.run([binary("sumo"), "--save-template", str(template)], check=True,
                       capture_output=True)
        table = template_table(template.read_text())
    version = subprocess.run([binary("sumo"), "--version"], capture_output=True,
                             text=True).stdout.splitlines()[0]
    path.write_text(json.dumps({"sumo": version, "options": table}, indent=0, sort_keys=True))
    return len(table)


if __name__ == "__main__":
    print(f"{OPTIONS_FILE}: {write_table()} options")
