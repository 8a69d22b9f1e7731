"""The fused CPU kernel of the A layer: sym4.c, compiled on first use, called through ctypes.

Why a C file, not inductor or a torch C++ extension. The kernel (sym4.c, sym4_body.h) is plain C11
that includes no torch header: the one build serves every torch version (the package declares
torch >= 2.4) and needs no torch build tools; compiling it takes 1-3 s with `cc -O3`. Inductor
(torch.compile of a functional Jacobi) also needs a C++ compiler at run time, compiles for tens of
seconds to minutes per process cache miss and per new shape, and its code changes with the torch
version; a torch C++ extension (`torch.utils.cpp_extension`) compiles against torch's headers for
30-60 s and must be rebuilt for every torch version it meets.

Build and cache. On the first call in a process that needs it, `library()` looks for
`sym4-<key>.so` in the cache directory (`$ROTLEARN_CACHE_DIR`, else `$XDG_CACHE_HOME/rotlearn`,
else `~/.cache/rotlearn`, subdirectory `kernels`); the key hashes the two source files, the
compiler (its path and `--version`), the flags and the platform, so a changed source or compiler
builds anew and a stale library is never loaded. Missing, it is compiled with `$CC` (else `cc`,
`gcc`, `clang`) into a temporary file and renamed into place (atomic: processes that build at the
same time each get a complete file). A library is loaded only from a directory and file owned by
this user and writable by no one else.

Without a compiler (or with ROTLEARN_CPU_KERNEL=0) the package runs as before on the eager path;
`sym4_eigh_min(kernel="auto")` falls back to it with one RuntimeWarning per process that says why,
`kernel="cpu"` raises that reason.

Threads: the kernel splits the batch over min(torch.get_num_threads(), B / 4096) POSIX threads
that it starts per call; every matrix is computed by the same instructions whatever the split, so
results are bit-identical for any thread count and any batch split.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import platform
import shutil
import stat
import subprocess
import sys
import tempfile
import threading
import warnings
from pathlib import Path

import torch
from torch import Tensor

__all__ = ["KernelUnavailableError", "available", "backward", "forward", "library"]

SOURCES = ("sym4.c", "sym4_body.h")
ABI = 1  # rotlearn_sym4_abi() of the sources in this directory
FLAGS = (
    "-O3",
    "-std=c11",
    "-fPIC",
    "-shared",
    "-pthread",
    "-ffp-contract=off",  # no FMA contraction: every SIMD width rounds alike
    "-fno-math-errno",  # sqrt as one instruction (its argument is never negative)
)
# x86-64: one function per instruction set (AVX-512, AVX2, baseline), picked at load time.
CLONES = "-DROTLEARN_TARGET_CLONES"
MATRICES_PER_THREAD = 4096  # below this a thread costs more to start than it saves
DISABLE_ENV = "ROTLEARN_CPU_KERNEL"  # "0": never build or load the kernel


class KernelUnavailableError(RuntimeError):
    """The fused CPU kernel cannot be used here; the message says why."""


_lock = threading.Lock()
_state: dict[str, object] = {}  # "lib" or "error", set once per process
_warned = False


def cache_dir() -> Path:
    """Where compiled kernels are kept: $ROTLEARN_CACHE_DIR, $XDG_CACHE_HOME/rotlearn or
    ~/.cache/rotlearn; subdirectory `kernels`."""
    root = os.environ.get("ROTLEARN_CACHE_DIR")
    if not root:
        xdg = os.environ.get("XDG_CACHE_HOME")
        root = str(Path(xdg) / "rotlearn") if xdg else str(Path.home() / ".cache" / "rotlearn")
    return Path(root) / "kernels"


def _compiler() -> str:
    for name in (os.environ.get("CC"), "cc", "gcc", "clang"):
        if name and (path := shutil.which(name)):
            return path
    raise KernelUnavailableError(
        "no C compiler found (set CC, or install gcc or clang); the eager solver is used"
    )


def _version(compiler: str) -> str:
    try:
        done = subprocess.run(
            [compiler, "--version"], capture_output=True, text=True, timeout=30, check=False
        )
    except (OSError, subprocess.SubprocessError) as error:
        raise KernelUnavailableError(f"{compiler} --version failed: {error}") from error
    return done.stdout.strip()


def _flag_sets() -> list[tuple[str, ...]]:
    if platform.machine().lower() in ("x86_64", "amd64"):
        return [(*FLAGS, CLONES), FLAGS]
    return [FLAGS]


def _key(sources: bytes, compiler: str, version: str, flags: tuple[str, ...]) -> str:
    text = "\0".join((compiler, version, " ".join(flags), sys.platform, platform.machine()))
    return hashlib.sha256(sources + text.encode()).hexdigest()[:20]


def _private(path: Path) -> bool:
    """Owned by this user and writable by no one else (a library loaded from it runs as code)."""
    info = path.stat()
    return info.st_uid == os.getuid() and not info.st_mode & (stat.S_IWGRP | stat.S_IWOTH)


def _compile(compiler: str, flags: tuple[str, ...], source: Path, target: Path) -> str | None:
    """Build `target` atomically; None on success, else the compiler's complaint."""
    fd, tmp = tempfile.mkstemp(prefix=target.stem, suffix=".tmp", dir=target.parent)
    os.close(fd)
    try:
        done = subprocess.run(
            [compiler, *flags, str(source), "-o", tmp, "-lm"],
            capture_output=True, text=True, timeout=300, check=False,
        )  # fmt: skip
        if done.returncode != 0:
            return (done.stderr or done.stdout).strip()[-2000:]
        os.chmod(tmp, 0o755)
        os.replace(tmp, target)
        return None
    except (OSError, subprocess.SubprocessError) as error:
        return str(error)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def _build() -> ctypes.CDLL:
    if os.environ.get(DISABLE_ENV) == "0":
        raise KernelUnavailableError(f"disabled by {DISABLE_ENV}=0; the eager solver is used")
    here = Path(__file__).resolve().parent
    sources = b"".join((here / name).read_bytes() for name in SOURCES)
    compiler = _compiler()
    version = _version(compiler)
    directory = cache_dir()
    try:
        directory.mkdir(parents=True, exist_ok=True, mode=0o700)
    except OSError as error:
        raise KernelUnavailableError(
            f"cannot create {directory}: {error} (set ROTLEARN_CACHE_DIR to a writable directory)"
        ) from error
    if not _private(directory):
        raise KernelUnavailableError(
            f"{directory} is not private to this user (owner or group/other write permission);"
            " set ROTLEARN_CACHE_DIR to a directory only you can write"
        )
    complaints = []
    for flags in _flag_sets():
        target = directory / f"sym4-{_key(sources, compiler, version, flags)}.so"
        if not target.exists():
            complaint = _compile(compiler, flags, here / "sym4.c", target)
            if complaint is not None:
                complaints.append(f"{compiler} {' '.join(flags)}: {complaint}")
                continue
        if not _private(target):
            raise KernelUnavailableError(f"{target} is writable by others; refusing to load it")
        lib = ctypes.CDLL(str(target))
        if lib.rotlearn_sym4_abi() != ABI:
            raise KernelUnavailableError(f"{target}: interface {lib.rotlearn_sym4_abi()} != {ABI}")
        return _declare(lib)
    raise KernelUnavailableError("compiling the CPU kernel failed:\n" + "\n".join(complaints))


def _declare(lib: ctypes.CDLL) -> ctypes.CDLL:
    ptr, i64, cint = ctypes.c_void_p, ctypes.c_int64, ctypes.c_int
    lib.rotlearn_sym4_forward.argtypes = [cint, ptr, i64, i64, i64, i64, cint, ptr, ptr, ptr, cint]
    lib.rotlearn_sym4_forward.restype = cint
    f64 = ctypes.c_double
    lib.rotlearn_sym4_backward.argtypes = [cint, ptr, ptr, ptr, ptr, f64, i64, ptr, cint]
    lib.rotlearn_sym4_backward.restype = cint
    return lib


def library() -> ctypes.CDLL:
    """The compiled kernel (built and cached on first use). Raises KernelUnavailableError."""
    state = _state
    if not state:
        with _lock:
            if not state:
                try:
                    state["lib"] = _build()
                except KernelUnavailableError as error:
                    state["error"] = error
    if "error" in state:
        raise state["error"]  # type: ignore[misc]
    return state["lib"]  # type: ignore[return-value]


def available(warn: bool = False) -> bool:
    """Whether the kernel can run in this process; with `warn`, a RuntimeWarning (once per
    process) names the reason when it cannot."""
    global _warned
    try:
        library()
        return True
    except KernelUnavailableError as error:
        if warn and not _warned:
            _warned = True
            warnings.warn(
                f"rotlearn: fused CPU eigensolver unavailable: {error}",
                RuntimeWarning,
                stacklevel=2,
            )
        return False


def _threads(batch: int) -> int:
    return max(1, min(torch.get_num_threads(), batch // MATRICES_PER_THREAD))


def forward(A: Tensor, rounds: int) -> tuple[Tensor, Tensor, Tensor]:
    """A (B, 4, 4) float32/float64 on the CPU (any strides; only the upper triangle is read) ->
    eigenvalues (B, 4) ascending, q (B, 4) canonical, V (B, 4, 4) (eigenvectors as columns)."""
    lib = library()
    B = A.shape[0]
    eigenvalues = A.new_empty(B, 4)
    q = A.new_empty(B, 4)
    V = A.new_empty(B, 4, 4)
    if B:
        lib.rotlearn_sym4_forward(
            A.dtype == torch.float64, A.data_ptr(), B, *A.stride(), rounds,
            eigenvalues.data_ptr(), q.data_ptr(), V.data_ptr(), _threads(B),
        )  # fmt: skip
    return eigenvalues, q, V


def backward(
    grad_l: Tensor | None, grad_q: Tensor | None, eigenvalues: Tensor, V: Tensor, gap_eps: float
) -> Tensor:
    """grad_A (B, 4, 4), exactly symmetric, from the output gradients (B, 4) (None: zero) and the
    saved eigenvalues (B, 4) and V (B, 4, 4)."""
    lib = library()
    B = V.shape[0]
    grad = V.new_empty(B, 4, 4)
    # Contiguous copies held in names: the kernel reads their memory after data_ptr() returns.
    gl = None if grad_l is None else grad_l.to(V.dtype).contiguous()
    gq = None if grad_q is None else grad_q.to(V.dtype).contiguous()
    lam, vec = eigenvalues.contiguous(), V.contiguous()
    if B:
        lib.rotlearn_sym4_backward(
            V.dtype == torch.float64,
            None if gl is None else gl.data_ptr(),
            None if gq is None else gq.data_ptr(),
            lam.data_ptr(), vec.data_ptr(), float(gap_eps), B, grad.data_ptr(), _threads(B),
        )  # fmt: skip
    return grad
