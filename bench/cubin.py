"""Compiled-resource readout of CUDA binaries (registers and stack per kernel), in pure Python.

A ``.cubin`` is an ELF file. The CUDA assembler records per-kernel resource attributes ("EIATTR")
in ``.nv.info`` sections (the module-wide ``.nv.info`` and the per-kernel ``.nv.info.<kernel>``):
a sequence of records ``format: u8, attribute: u8`` followed by a value whose layout the format
gives (``EIFMT_NVAL`` 0x01: none; ``EIFMT_BVAL`` 0x02: one byte; ``EIFMT_HVAL`` 0x03: a u16;
``EIFMT_SVAL`` 0x04: a u16 byte count then that many bytes); a zero byte where a record would
start is one byte of padding (it follows a BVAL, keeping the records 4-byte aligned). The resource attributes are SVAL
records holding ``(symbol index of the kernel: u32, value: u32)``:

====================  ====  ============================================================
attribute             code  value
====================  ====  ============================================================
EIATTR_FRAME_SIZE     0x11  bytes of stack frame of the function itself
EIATTR_MIN_STACK_SIZE 0x12  bytes of stack needed when calling this kernel (with callees)
EIATTR_MAX_STACK_SIZE 0x23  bytes of stack of the deepest call chain
EIATTR_REGCOUNT       0x2f  registers per thread
====================  ====  ============================================================

The codes are those printed by ``cuobjdump -elf`` / ``nvdisasm`` (e.g. ``.byte 0x04, 0x2f`` =
SVAL, EIATTR_REGCOUNT) and listed by open-source cubin tools (GVirtuS' ``CudaRtInternal.h``,
cricket's ``cpu-elf2.h``). A non-zero stack on a kernel that calls nothing means local memory:
arrays indexed at run time or register spills, which cost global-memory traffic on the GPU.

Used by ``tests/kernels/test_kernel_resources.py`` to hold the kernels' registers and stack to bounds
(the binaries come from :func:`warp.compile_aot_module`, which needs no GPU).
"""
from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

EIFMT_NONE = 0x00
EIFMT_NVAL = 0x01
EIFMT_BVAL = 0x02
EIFMT_HVAL = 0x03
EIFMT_SVAL = 0x04

EIATTR_FRAME_SIZE = 0x11
EIATTR_MIN_STACK_SIZE = 0x12
EIATTR_MAX_STACK_SIZE = 0x23
EIATTR_REGCOUNT = 0x2F

_FIELDS = {
    EIATTR_REGCOUNT: "registers",
    EIATTR_FRAME_SIZE: "frame",
    EIATTR_MIN_STACK_SIZE: "min_stack",
    EIATTR_MAX_STACK_SIZE: "max_stack",
}


@dataclass(frozen=True)
class KernelResources:
    """Resources of one compiled kernel: ``registers`` per thread; ``frame`` (its own stack frame),
    ``min_stack`` and ``max_stack`` in bytes per thread (-1 where the binary does not record it)."""

    name: str
    registers: int = -1
    frame: int = -1
    min_stack: int = -1
    max_stack: int = -1

    @property
    def stack(self) -> int:
        """The largest of the recorded stack figures (bytes of local memory per thread)."""
        return max(self.frame, self.min_stack, self.max_stack, 0)


def _sections(data: bytes) -> list[tuple[str, int, bytes, int]]:
    """(name, type, contents, link) of every section of a 64-bit little-endian ELF."""
    if data[:4] != b"\x7fELF":
        raise ValueError("not an ELF file (a .cubin starts with \\x7fELF)")
    if data[4] != 2 or data[5] != 1:
        raise ValueError("only 64-bit little-endian ELF (every cubin) is supported")
    e_shoff, = struct.unpack_from("<Q", data, 0x28)
    e_shentsize, e_shnum, e_shstrndx = struct.unpack_from("<HHH", data, 0x3A)
    raw = []
    for i in range(e_shnum):
        name, typ, _flags, _addr, off, size, link = struct.unpack_from("<IIQQQQI", data, e_shoff + i * e_shentsize)
        raw.append((name, typ, data[off:off + size] if typ != 8 else b"", link))  # 8 = SHT_NOBITS
    strtab = raw[e_shstrndx][2]

    def cstr(tab: bytes, at: int) -> str:
        return tab[at:tab.index(b"\0", at)].decode("ascii", "replace")

    return [(cstr(strtab, n), t, c, link) for n, t, c, link in raw]


def _symbols(sections) -> list[str]:
    """Symbol names of ``.symtab`` by index."""
    for name, typ, body, link in sections:
        if typ == 2:  # SHT_SYMTAB
            names = sections[link][2]
            out = []
            for k in range(len(body) // 24):
                st_name, = struct.unpack_from("<I", body, k * 24)
                out.append(names[st_name:names.index(b"\0", st_name)].decode("ascii", "replace"))
            return out
    return []


def _records(body: bytes):
    """(format, attribute, value bytes) of the EIATTR records of one .nv.info section."""
    at = 0
    while at + 2 <= len(body):
        fmt, attr = body[at], body[at + 1]
        at += 2
        if fmt == EIFMT_NONE:  # one padding byte (records are 4-byte aligned after a BVAL)
            at -= 1
            continue
        if fmt == EIFMT_NVAL:
            val = b""
        elif fmt == EIFMT_BVAL:
            val = body[at:at + 1]
            at += 1
        elif fmt == EIFMT_HVAL:
            val = body[at:at + 2]
            at += 2
        elif fmt == EIFMT_SVAL:
            size, = struct.unpack_from("<H", body, at)
            val = body[at + 2:at + 2 + size]
            at += 2 + size
        else:
            raise ValueError(f"unknown EIATTR record format 0x{fmt:02x} at byte {at - 2}")
        yield fmt, attr, val


def kernel_resources(cubin: bytes | str | Path) -> dict[str, KernelResources]:
    """Registers and stack of every kernel of a cubin (bytes or a path), keyed by mangled name.

    Raises ValueError when the data is not a 64-bit ELF or holds malformed EIATTR records.
    """
    if isinstance(cubin, (str, Path)):
        cubin = Path(cubin).read_bytes()
    if not isinstance(cubin, (bytes, bytearray)):
        raise ValueError(f"cubin must be bytes or a path, got {type(cubin).__name__}")
    sections = _sections(bytes(cubin))
    symbols = _symbols(sections)
    found: dict[str, dict[str, int]] = {}
    for name, _typ, body, _link in sections:
        if not name.startswith(".nv.info"):
            continue
        for fmt, attr, val in _records(body):
            if attr in _FIELDS and fmt == EIFMT_SVAL and len(val) == 8:
                sym, value = struct.unpack("<II", val)
                kname = symbols[sym] if sym < len(symbols) else name[len(".nv.info."):]
                found.setdefault(kname, {})[_FIELDS[attr]] = value
    # the kernels are the functions with a .text.<name> section
    kernels = {n[len(".text."):] for n, *_ in sections if n.startswith(".text.")}
    return {k: KernelResources(k, **v) for k, v in sorted(found.items()) if k in kernels}


def occupancy_warps(registers: int, block_dim: int, regs_per_sm: int = 65536, max_warps: int = 64,
                    max_blocks: int = 32, alloc_unit: int = 256) -> int:
    """Resident warps per SM allowed by ``registers`` per thread at ``block_dim`` threads per block.

    Defaults are Hopper's (sm_90: 64 K registers and 64 warps per SM, at most 32 blocks, registers
    allocated per warp in units of 256). Shared memory is not counted (these kernels use none).
    """
    if registers <= 0 or block_dim <= 0:
        raise ValueError(f"registers and block_dim must be positive, got {registers}, {block_dim}")
    warps_per_block = -(-block_dim // 32)
    per_warp = -(-registers * 32 // alloc_unit) * alloc_unit
    warps_by_regs = regs_per_sm // per_warp
    blocks = min(warps_by_regs // warps_per_block, max_warps // warps_per_block, max_blocks)
    return blocks * warps_per_block
