"""An image's XMP packet, read safely and tolerantly: decoded as it declares, DTDs refused, camera quirks mended.

XMP is RDF/XML in a packet (``<?xpacket begin=...?> <x:xmpmeta> ... </x:xmpmeta> <?xpacket end=...?>``), UTF-8 by
default, UTF-16 or UTF-32 when its byte-order mark or XML declaration says so. What is done, in order:

1. the bytes are decoded with the packet's byte-order mark, else the encoding the XML 1.0 spec (appendix F) detects
   from its first bytes or its XML declaration names, else UTF-8;
2. the decoded text is refused if it declares a DTD or entities (``<!DOCTYPE``, ``<!ENTITY``, any ``<!`` that is not
   a comment or CDATA): XMP never does, and entity expansion is how XML parsers are attacked. The check runs on the
   text, so a UTF-16 packet cannot hide ``<!DOCTYPE`` from it, and the parser is then given that same text as UTF-8;
3. only the ``x:xmpmeta`` (or ``rdf:RDF``) element is parsed: the wrapper around it is optional in XMP and cameras
   damage it (the Zenmuse XT S ends its packet with two NUL bytes instead of ``>``);
4. a namespace declared twice with the same URI on one element (``xmlns:DJI="http://www.dji.com"`` twice, Zenmuse
   XT S) is declared once; anything else that is not well-formed XML is an error.
"""

from __future__ import annotations

import codecs
import re
import xml.etree.ElementTree as ET
from io import BytesIO

from dapm_lightning.inference.telemetry.pose import TelemetryError

MAX_XMP_BYTES = 4 << 20
"""A larger packet is not read (a JPEG's XMP segment holds 64 KiB; extended XMP a few MiB at most)."""

_BOMS = ((codecs.BOM_UTF32_LE, "utf-32-le"), (codecs.BOM_UTF32_BE, "utf-32-be"), (codecs.BOM_UTF8, "utf-8"),
         (codecs.BOM_UTF16_LE, "utf-16-le"), (codecs.BOM_UTF16_BE, "utf-16-be"))
_SNIFF = ((b"\x00\x00\x00<", "utf-32-be"), (b"<\x00\x00\x00", "utf-32-le"), (b"\x00<\x00", "utf-16-be"),
          (b"<\x00", "utf-16-le"))
_DECLARED = re.compile(rb"^\s*<\?xml[^>]*?encoding\s*=\s*[\"']([A-Za-z0-9._-]+)[\"']")
_DTD = re.compile(r"<!(?!--|\[CDATA\[)")
_XML_DECLARATION = re.compile(r"^\s*<\?xml\b[^>]*\?>")
_ROOT = re.compile(r"<((?:[A-Za-z_][\w.-]*:)?(?:xmpmeta|xapmeta|RDF))[\s>/]")
_START_TAG = re.compile(r"<[A-Za-z_](?:[^<>\"']|\"[^\"]*\"|'[^']*')*>")
_ATTRIBUTE = re.compile(r"\s+([^\s=/>]+)\s*=\s*(\"[^\"]*\"|'[^']*')")


def decode_xmp(packet: bytes, where: str) -> str:
    """The packet's text, decoded as its byte-order mark, first bytes or XML declaration say (else UTF-8).

    Raises:
        TelemetryError: the packet is too large or is not text in that encoding (``where`` names the image).
    """
    if len(packet) > MAX_XMP_BYTES:
        raise TelemetryError(f"{where}: its XMP packet is {len(packet)} bytes, more than any camera writes "
                             f"({MAX_XMP_BYTES}); not read")
    encoding, start = "utf-8", 0
    for bom, name in _BOMS:
        if packet.startswith(bom):
            encoding, start = name, len(bom)
            break
    else:
        sniffed = next((name for head, name in _SNIFF if packet.startswith(head)), None)
        declared = _DECLARED.match(packet)
        encoding = sniffed or (declared.group(1).decode("ascii") if declared else "utf-8")
    try:
        text = packet[start:].decode(encoding)
    except (LookupError, UnicodeDecodeError) as exc:
        raise TelemetryError(f"{where}: its XMP packet is not {encoding} text ({exc})") from None
    return text.strip("\x00 \t\r\n\ufeff")


def _declare_once(tag: re.Match[str]) -> str:
    """A start tag with a namespace declared twice with the same URI declared once (other duplicates kept)."""
    text = tag.group(0)
    seen: dict[str, str] = {}
    duplicates: list[tuple[int, int]] = []
    for attribute in _ATTRIBUTE.finditer(text):
        name, value = attribute.group(1), attribute.group(2)[1:-1]
        if name.startswith("xmlns") and seen.get(name) == value:
            duplicates.append(attribute.span())
        seen.setdefault(name, value)
    for begin, end in reversed(duplicates):
        text = text[:begin] + text[end:]
    return text


def parse_xmp(packet: bytes, where: str) -> tuple[ET.Element, dict[str, str]]:
    """The packet's ``x:xmpmeta`` element and its namespaces ``{uri: prefix as written}``.

    Raises:
        TelemetryError: a DTD or an entity declaration, text that is not in its encoding, or XML that is not
            well-formed once the quirks above are mended; the message names ``where`` and the fix.
    """
    text = decode_xmp(packet, where)
    if (dtd := _DTD.search(text)) is not None:
        raise TelemetryError(f"{where}: its XMP packet declares a DTD / entities ({text[dtd.start():dtd.start() + 9]!r}"
                             "...), which XMP never does; refusing to parse it")
    text = _XML_DECLARATION.sub("", text, count=1)
    root = _ROOT.search(text)
    if root is not None:
        end = text.rfind(f"</{root.group(1)}>")
        if end > root.start():
            text = text[root.start():end + len(root.group(1)) + 3]
    text = _START_TAG.sub(_declare_once, text)
    namespaces: dict[str, str] = {}
    try:
        events = ET.iterparse(BytesIO(text.encode("utf-8")), events=("start-ns", "end"))
        element: ET.Element | None = None
        for event, item in events:
            if event == "start-ns":
                prefix, uri = item
                namespaces.setdefault(uri, prefix)
            else:
                element = item
    except ET.ParseError as exc:
        raise TelemetryError(f"{where}: its XMP packet is not well-formed XML ({exc})") from None
    if element is None:
        raise TelemetryError(f"{where}: its XMP packet holds no XML element")
    return element, namespaces


def qualified(name: str, namespaces: dict[str, str]) -> str:
    """``{uri}local`` as written in the file, ``prefix:local`` (``drone-dji:RelativeAltitude``)."""
    if not name.startswith("{"):
        return name
    uri, local = name[1:].split("}", 1)
    prefix = namespaces.get(uri, "")
    return f"{prefix}:{local}" if prefix else local


def local_name(name: str) -> str:
    """An XML name without its namespace: ``{http://www.dji.com}GimbalRollDegree`` -> ``GimbalRollDegree``."""
    return name.rsplit("}", 1)[-1]


def namespace(name: str) -> str:
    """The namespace URI of ``{uri}local`` (``""`` without one)."""
    return name[1:].split("}", 1)[0] if name.startswith("{") else ""
