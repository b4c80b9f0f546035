"""KUKA RobotSensorInterface (RSI) datagrams: the controller's `<Rob>` in, keo's `<Sen>` out.

Every interpolation cycle (4 ms, or 12 ms on older controllers) the controller's ETHERNET
object sends one XML document over UDP and waits for the answer, which must echo its `IPOC`:

    <Rob Type="KUKA">
      <RIst X=".." Y=".." Z=".." A=".." B=".." C=".."/>      actual TCP pose, mm and degrees
      <AIPos A1=".." A2=".." A3=".." A4=".." A5=".." A6=".."/>  actual axis angles, degrees
      <EIPos E1=".." ... E6=".."/>                            external axes (optional)
      <IPOC>123645634563</IPOC>                               the controller's ms counter
    </Rob>

    <Sen Type="ImFree"><RKorr X=".." Y=".." Z=".." A=".." B=".." C=".." /><IPOC>..</IPOC></Sen>

Pure codec: bytes in, typed frames out, no I/O. Parsing uses the standard library's
ElementTree (expat). RSI documents are small and come from one configured controller, so the
guard against hostile XML is simple and strict: a datagram longer than MAX_DATAGRAM or one
with a document type declaration (`<!DOCTYPE`/`<!ENTITY`, which RSI never sends and which is
where entity expansion attacks live) is refused before expat sees it; expat >= 2.4 also
limits entity amplification itself. Python's expat never fetches external entities.
Elements the codec does not use (RSol, ASPos, Delay, DiL, Tech, ...) are ignored.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass

from keo_service.core.errors import KeoError
from keo_service.core.rejects import RejectLog

MAX_DATAGRAM = 8192  # a full RSI document with every standard element is ~1.5 kB
AXES = ("A1", "A2", "A3", "A4", "A5", "A6")
EXTERNAL_AXES = ("E1", "E2", "E3", "E4", "E5", "E6")
POSE = ("X", "Y", "Z", "A", "B", "C")
DEFAULT_SEN_TYPE = "ImFree"
IPOC_MAX = 2**64 - 1


@dataclass(frozen=True)
class RobFrame:
    """One `<Rob>` datagram: axes in degrees, the TCP pose in mm and degrees (A about Z, B
    about Y, C about X), external axes as sent (degrees or mm) when present."""

    ipoc: int
    axes_deg: tuple[float, ...]
    tcp: tuple[float, ...] | None  # RIst X Y Z A B C
    external: tuple[float, ...] | None  # EIPos E1..E6
    delay: int | None  # the controller's count of late answers (<Delay D=".."/>), if sent


@dataclass(frozen=True)
class SenFrame:
    """One `<Sen>` answer as the controller reads it."""

    sen_type: str
    ipoc: int
    rkorr: tuple[float, ...] | None  # X Y Z mm, A B C degrees
    akorr: tuple[float, ...] | None  # axis corrections, degrees


def _fmt(value: float) -> str:
    # six decimals, as the open drivers write (std::to_string): 1 nm and 1e-6 degree steps
    return f"{value:.6f}"


def format_sen(
    ipoc: int,
    rkorr: tuple[float, ...] | list[float] | None = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
    sen_type: str = DEFAULT_SEN_TYPE,
    akorr: tuple[float, ...] | list[float] | None = None,
) -> bytes:
    """The answer to the datagram numbered `ipoc`: `RKorr` (X Y Z mm, A B C degrees) and/or
    `AK` (A1..A6 degrees) corrections, then the echoed IPOC; no XML declaration, no spaces
    between elements (the layout the open drivers send and the controller accepts)."""
    root = ET.Element("Sen", {"Type": sen_type})
    if rkorr is not None:
        ET.SubElement(root, "RKorr", {k: _fmt(v) for k, v in zip(POSE, rkorr, strict=True)})
    if akorr is not None:
        ET.SubElement(root, "AK", {k: _fmt(v) for k, v in zip(AXES, akorr, strict=True)})
    ET.SubElement(root, "IPOC").text = str(ipoc)
    return ET.tostring(root, encoding="unicode").encode("ascii")


def format_rob(
    ipoc: int,
    axes_deg: tuple[float, ...] | list[float],
    tcp: tuple[float, ...] | list[float] = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
    external: tuple[float, ...] | list[float] | None = None,
    delay: int = 0,
) -> bytes:
    """A controller's datagram (for the mock controller), in the manual's element order."""
    root = ET.Element("Rob", {"Type": "KUKA"})
    ET.SubElement(root, "RIst", {k: repr(float(v)) for k, v in zip(POSE, tcp, strict=True)})
    ET.SubElement(root, "AIPos", {k: repr(float(v)) for k, v in zip(AXES, axes_deg, strict=True)})
    if external is not None:
        ET.SubElement(
            root, "EIPos", {k: repr(float(v)) for k, v in zip(EXTERNAL_AXES, external, strict=True)}
        )
    ET.SubElement(root, "Delay", {"D": str(delay)})
    ET.SubElement(root, "IPOC").text = str(ipoc)
    return ET.tostring(root, encoding="unicode").encode("ascii")


class _RefusedError(KeoError, ValueError):
    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


def _document(data: bytes, root_tag: str) -> ET.Element:
    if len(data) > MAX_DATAGRAM:
        raise _RefusedError("too_long", f"datagram of {len(data)} bytes, limit {MAX_DATAGRAM}")
    if b"<!" in data:
        raise _RefusedError("dtd", "a document type or entity declaration; RSI sends none")
    try:
        root = ET.fromstring(data)
    except ET.ParseError as exc:
        raise _RefusedError("malformed", f"not XML: {exc}") from None
    if root.tag != root_tag:
        raise _RefusedError("unexpected_root", f"<{root.tag}>, expected <{root_tag}>")
    return root


def _numbers(root: ET.Element, tag: str, keys: tuple[str, ...]) -> tuple[float, ...] | None:
    element = root.find(tag)
    if element is None:
        return None
    try:
        values = tuple(float(element.attrib[k]) for k in keys)
    except KeyError as exc:
        raise _RefusedError("missing_field", f"<{tag}> without {exc.args[0]}") from None
    except ValueError as exc:
        raise _RefusedError("not_a_number", f"<{tag}>: {exc}") from None
    if not all(math.isfinite(v) for v in values):
        raise _RefusedError("non_finite", f"<{tag}> {values!r}")
    return values


def _ipoc(root: ET.Element) -> int:
    element = root.find("IPOC")
    if element is None or element.text is None:
        raise _RefusedError("missing_field", "no <IPOC>")
    try:
        ipoc = int(element.text.strip())
    except ValueError:
        raise _RefusedError("not_a_number", f"<IPOC> {element.text!r}") from None
    if not 0 <= ipoc <= IPOC_MAX:
        raise _RefusedError("not_a_number", f"<IPOC> {ipoc} outside 0..2^64-1")
    return ipoc


class RsiCodec:
    """Parses `<Rob>` datagrams (and, for the mock controller, `<Sen>` answers); bad
    datagrams are counted by reason in `counters` and described in `messages`."""

    def __init__(self) -> None:
        self._rejects = RejectLog(keep=16)
        self.counters = self._rejects.counters
        self.messages = self._rejects.messages
        self.datagrams = 0  # datagrams parsed so far: a reject names its number

    def _next_datagram(self) -> None:
        self.datagrams += 1
        self._rejects.at = f"datagram {self.datagrams}"

    def parse_rob(self, data: bytes) -> RobFrame | None:
        self._next_datagram()
        try:
            root = _document(data, "Rob")
            ipoc = _ipoc(root)
            axes = _numbers(root, "AIPos", AXES)
            if axes is None:
                raise _RefusedError("missing_field", f"IPOC {ipoc}: no <AIPos>")
            tcp = _numbers(root, "RIst", POSE)
            external = _numbers(root, "EIPos", EXTERNAL_AXES)
            delay_el = root.find("Delay")
            delay = None
            if delay_el is not None and "D" in delay_el.attrib:
                try:
                    delay = int(float(delay_el.attrib["D"]))
                except (ValueError, OverflowError):  # "1e999" is a float, but inf no int
                    raise _RefusedError(
                        "not_a_number", f"<Delay D={delay_el.attrib['D']!r}>"
                    ) from None
        except _RefusedError as exc:
            self._rejects.reject(exc.reason, str(exc))
            return None
        self.counters["frames"] += 1
        return RobFrame(ipoc, axes, tcp, external, delay)

    def parse_sen(self, data: bytes) -> SenFrame | None:
        self._next_datagram()
        try:
            root = _document(data, "Sen")
            ipoc = _ipoc(root)
            rkorr = _numbers(root, "RKorr", POSE)
            akorr = _numbers(root, "AK", AXES)
        except _RefusedError as exc:
            self._rejects.reject(exc.reason, str(exc))
            return None
        self.counters["frames"] += 1
        return SenFrame(root.attrib.get("Type", ""), ipoc, rkorr, akorr)
