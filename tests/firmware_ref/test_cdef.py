"""The cffi declarations (firmware_ref/build_ffi.py ``CDEF``) are checked against the header they
copy (include/capsheet_fw.h): every function prototype identical, every struct's fields the same
(in order; a partial struct ``...;`` lists a subset), every enum value and macro name present. cffi
itself then checks sizes and offsets against the compiler when it builds the module."""

from __future__ import annotations

import re
from pathlib import Path

FW = Path(__file__).resolve().parents[2] / "firmware_ref"


def _cdef_text() -> str:
    src = (FW / "build_ffi.py").read_text()
    start = src.index('CDEF = r"""') + len('CDEF = r"""')
    return src[start:src.index('"""', start)].replace("MUTANT_FIELDS", "")  # the production build's


def _clean(t: str) -> str:
    t = re.sub(r"/\*.*?\*/", " ", t, flags=re.S)
    t = re.sub(r"\bCAPSHEET_WARN_UNUSED\s+", "", t)  # an attribute for the compiler, not the ABI cffi checks
    return re.sub(r"^\s*#(?!define).*$", "", t, flags=re.M)


def _norm(s: str) -> str:
    s = " ".join(s.split())
    return re.sub(r"\s*([*\[\](),])\s*", r"\1", s)


def prototypes(text: str) -> dict[str, str]:
    t = _clean(text)
    return {m.group(2): _norm(f"{m.group(1)} {m.group(2)}({m.group(3)})")
            for m in re.finditer(r"^([A-Za-z_][\w \*]*?)\b(capsheet_\w+)\s*\(([^;{]*?)\)\s*;", t, re.M)}


def _body(t: str, name: str) -> str | None:
    m = re.search(r"\}\s*" + re.escape(name) + r"\s*;", t)
    if not m:
        return None
    depth, i = 0, m.start()
    while i >= 0:
        depth += t[i] == "}"
        depth -= t[i] == "{"
        if depth == 0:
            return t[i + 1:m.start()]
        i -= 1
    return None


def fields(decl: str) -> list[str]:
    """``uint8_t a, b; struct {...} u;`` -> ["uint8_t a", "uint8_t b", "struct{...} u"] (normalised)."""
    out, depth, cur = [], 0, ""
    for ch in decl:
        depth += ch == "{"
        depth -= ch == "}"
        if ch == ";" and depth == 0:
            cur = cur.strip()
            if cur:
                if "{" in cur:
                    out.append(_norm(re.sub(r"\{(.*)\}", lambda m: "{" + ";".join(fields(m.group(1))) + "}", cur,
                                            flags=re.S)))
                else:
                    head, *rest = [p.strip() for p in cur.split(",")]
                    typ, first = head.rsplit(" ", 1) if " " in head else ("", head)
                    out += [_norm(f"{typ} {first}")] + [_norm(f"{typ} {r}") for r in rest]
            cur = ""
        else:
            cur += ch
    return out


def structs(text: str) -> dict[str, list[str]]:
    t = _clean(text)
    names = re.findall(r"\}\s*(capsheet_\w+_t)\s*;", t)
    return {n: fields(_body(t, n)) for n in names if re.search(r"typedef\s+struct", t)}


def enums(text: str) -> dict[str, int]:
    t = _clean(text)
    return {k: int(v, 0) for body in re.findall(r"typedef\s+enum\s*\{(.*?)\}", t, re.S)
            for k, v in re.findall(r"(CAPSHEET_\w+)\s*=\s*(0x[0-9A-Fa-f]+|\d+)", body)}


def mismatches(header: str, cdef: str) -> list[str]:
    bad = []
    hp, cp = prototypes(header), prototypes(cdef)
    bad += [f"function {n}: header {hp.get(n)!r}, cdef {cp.get(n)!r}" for n in sorted(set(hp) | set(cp))
            if hp.get(n) != cp.get(n)]
    hs, cs = structs(header), structs(cdef)
    for n, cf in cs.items():
        hf = hs.get(n)
        if hf is None:
            bad.append(f"struct {n} not in the header")
        elif "..." in cf:
            bad += [f"struct {n}: field {f!r} not in the header" for f in cf if f != "..." and f not in hf]
        elif cf != hf:
            bad.append(f"struct {n}: header {hf}, cdef {cf}")
    he, ce = enums(header), enums(cdef)
    bad += [f"enum {k}: header {he.get(k)}, cdef {v}" for k, v in ce.items() if he.get(k) != v]
    hm = set(re.findall(r"#define\s+(CAPSHEET_\w+)", header))
    bad += [f"macro {m} not in the header" for m in re.findall(r"#define\s+(CAPSHEET_\w+)", cdef) if m not in hm]
    return bad


def test_the_cdef_matches_the_header():
    header = (FW / "include/capsheet_fw.h").read_text()
    cdef = _cdef_text()
    assert len(prototypes(cdef)) == len(prototypes(header)) >= 20
    assert {"capsheet_msg_t", "capsheet_hal_t", "capsheet_chip_t"} <= set(structs(cdef))
    assert mismatches(header, cdef) == []


def test_every_fallible_function_is_marked_warn_unused():
    # the negative CAPSHEET_ERR_* convention: every function and HAL callback returning int32_t can
    # fail, and a caller may not drop its result (CAPSHEET_WARN_UNUSED; test_build.py shows the
    # strict build refusing a caller that does)
    header = re.sub(r"/\*.*?\*/", " ", (FW / "include/capsheet_fw.h").read_text(), flags=re.S)
    functions = re.findall(r"^(.*?)\bint32_t (capsheet_\w+)\(", header, re.M)
    callbacks = re.findall(r"^(.*?)\bint32_t \(\*(\w+)\)\(", header, re.M)
    assert len(functions) >= 18 and {n for _, n in callbacks} >= {"read_axes", "send_bytes", "send_can"}
    assert [n for pre, n in functions + callbacks if "CAPSHEET_WARN_UNUSED" not in pre] == []
    # and nothing that cannot fail is marked (a uint16_t CRC, a bool, a void)
    marked = re.findall(r"^\s*CAPSHEET_WARN_UNUSED\s+(\w+)", header, re.M)
    assert set(marked) == {"int32_t"}


def test_a_drifted_cdef_is_caught():
    header = (FW / "include/capsheet_fw.h").read_text()
    cdef = _cdef_text()
    drifts = [("uint8_t axis; uint8_t flags; int16_t offset_q4;", "uint8_t axis; uint16_t flags; int16_t offset_q4;"),
              ("int32_t capsheet_chip_poll(capsheet_chip_t *chip, uint64_t now_us);",
               "int32_t capsheet_chip_poll(capsheet_chip_t *chip, uint32_t now_us);"),
              ("CAPSHEET_CAN_FD = 2", "CAPSHEET_CAN_FD = 3"),
              ("    uint16_t last_sync;\n", "    uint16_t last_sync_counter;\n")]
    for old, new in drifts:
        assert old in cdef, old
        assert mismatches(header, cdef.replace(old, new)) != [], new
