"""Build the se3sync plant FMU (FMI 2.0 or FMI 3.0 Co-Simulation) from its C sources.

``fmu_path(n)`` returns a cached ``.fmu`` for ``n`` bodies, building it on first use into
``$SE3SYNC_CACHE`` (default ``~/.cache/se3sync/fmu``); the cache key is a hash of the C
sources, of this file and of layout.py, of ``n``, of the FMI version and of the platform.
``fmi_version=2`` (the default) builds an FMI 2.0 FMU from model.c + fmi2.c,
``fmi_version=3`` an FMI 3.0 FMU from model.c + fmi3.c (same model, same layout; FMI 3.0
adds the independent variable ``time`` at value reference 0).  Every file is
written to a temporary name and renamed into place, so concurrent processes never see a
half-written FMU.
"""
from __future__ import annotations

import hashlib
import os
import platform as _platform
import shlex
import shutil
import subprocess
import sys
import tempfile
import threading
import uuid
import zipfile
from pathlib import Path

from controller.errors import Se3SyncError

from . import layout

MODEL_IDENTIFIER = "se3sync_plant"
C_DIR = Path(__file__).resolve().parent / "c"
C_SOURCES = ("model.c", "fmi2.c")
C_HEADERS = ("model.h", "rkmk4.h", "fmi2Functions.h", "fmi2FunctionTypes.h", "fmi2TypesPlatform.h")
C_SOURCES_FMI3 = ("model.c", "fmi3.c")
C_HEADERS_FMI3 = ("model.h", "rkmk4.h", "fmi3Functions.h", "fmi3FunctionTypes.h", "fmi3PlatformTypes.h")
# the version-independent part of both FMI layers: #included by fmi2.c and fmi3.c (so it is
# compiled as part of them and <SourceFiles> stays model.c + fmiN.c), shipped in sources/
C_COMMON = ("fmu_common.h", "fmu_common.c")
FMI_VERSIONS = (2, 3)
VR_TIME = 0  # FMI 3.0 only: the independent variable
CFLAGS = ("-O3", "-fPIC", "-shared", "-ffp-contract=off")

UNITS = {  # name: SI base-unit exponents
    "kg": dict(kg=1),
    "kg.m2": dict(kg=1, m=2),
    "m": dict(m=1),
    "m/s": dict(m=1, s=-1),
    "m/s2": dict(m=1, s=-2),
    "rad/s": dict(rad=1, s=-1),
    "N": dict(kg=1, m=1, s=-2),
    "N.m": dict(kg=1, m=2, s=-2),
    "s": dict(s=1),
    "N.s/m": dict(kg=1, s=-1),
    "N.m.s/rad": dict(kg=1, m=2, s=-1, rad=-1),
}

LOG_CATEGORIES = (
    ("logEvents", "instantiation and other events"),
    ("logStatusWarning", "messages with status fmi2Warning (e.g. q0 normalised)"),
    ("logStatusDiscard", "messages with status fmi2Discard (status queries)"),
    ("logStatusError", "messages with status fmi2Error (refused values, illegal calls)"),
    ("logStatusFatal", "messages with status fmi2Fatal"),
    ("logCalls", "FMI function calls"),
    ("logAll", "all of the above"),
)

_lock = threading.Lock()
_memo: dict[tuple[int, int, str], Path] = {}


class BuildError(Se3SyncError):
    """The FMU could not be built (no compiler, compiler failure, bad arguments)."""


def check_n_bodies(n_bodies) -> int:
    try:
        n = int(n_bodies)
    except (TypeError, ValueError):
        raise BuildError(f"number of bodies must be an integer, got {n_bodies!r}") from None
    if n != n_bodies or not 1 <= n <= layout.MAX_BODIES:
        raise BuildError(f"number of bodies must be an integer in 1..{layout.MAX_BODIES}, got {n_bodies!r}")
    return n


def check_fmi_version(fmi_version) -> int:
    if isinstance(fmi_version, bool) or fmi_version not in FMI_VERSIONS:
        raise BuildError(f"FMI version must be 2 or 3, got {fmi_version!r}")
    return int(fmi_version)


def _sources(fmi_version: int) -> tuple[tuple[str, ...], tuple[str, ...]]:
    return (C_SOURCES, C_HEADERS + C_COMMON) if fmi_version == 2 else (C_SOURCES_FMI3, C_HEADERS_FMI3 + C_COMMON)


def platform_tuple() -> str:
    """FMI 3.0 binaries folder name of this machine (x86_64-linux, aarch64-darwin, ...)."""
    machine = _platform.machine().lower()
    if machine in ("amd64", "x86_64", "x64", "i386", "i686", "x86"):
        arch = "x86_64" if sys.maxsize > 2**32 else "x86"
    elif machine in ("arm64", "aarch64"):
        arch = "aarch64"
    else:
        arch = machine
    system = {"Linux": "linux", "Darwin": "darwin", "Windows": "windows"}.get(_platform.system(),
                                                                          _platform.system().lower())
    return f"{arch}-{system}"


def binaries_folder(fmi_version: int = 2) -> str:
    """Name of the binaries/ subfolder for this machine: platform_tag() (FMI 2.0) or platform_tuple() (FMI 3.0)."""
    return platform_tag() if check_fmi_version(fmi_version) == 2 else platform_tuple()


def platform_tag() -> str:
    """FMI 2.0 binaries folder name of this machine (linux64, darwin64, win64, ...)."""
    bits = "64" if sys.maxsize > 2**32 else "32"
    system = _platform.system()
    if system == "Linux":
        return "linux" + bits
    if system == "Darwin":
        return "darwin" + bits
    if system == "Windows":
        return "win" + bits
    return system.lower() + bits


def _shared_library_suffix() -> str:
    return {"Darwin": ".dylib", "Windows": ".dll"}.get(_platform.system(), ".so")


def source_hash() -> str:
    """sha256 over the C sources/headers and the Python files that generate the FMU."""
    h = hashlib.sha256()
    names = dict.fromkeys(C_SOURCES + C_HEADERS + C_SOURCES_FMI3 + C_HEADERS_FMI3 + C_COMMON + ("config.h",))
    files = [C_DIR / f for f in names]
    files += [Path(__file__).resolve(), Path(layout.__file__).resolve()]
    for f in files:
        h.update(f.name.encode())
        h.update(b"\0")
        h.update(f.read_bytes())
        h.update(b"\0")
    return h.hexdigest()


def guid(n_bodies: int, fmi_version: int = 2) -> str:
    """GUID (FMI 2.0) / instantiationToken (FMI 3.0) of the FMU for ``n_bodies`` bodies."""
    n = check_n_bodies(n_bodies)
    v = check_fmi_version(fmi_version)
    digest = hashlib.sha256((f"{source_hash()}:{n}" + ("" if v == 2 else ":fmi3")).encode()).digest()
    return "{" + str(uuid.UUID(bytes=digest[:16], version=5)) + "}"


def find_compiler() -> list[str]:
    """The C compiler command: $CC if set, else cc, gcc or clang from PATH."""
    cc = os.environ.get("CC")
    if cc:
        cmd = shlex.split(cc)
        if cmd and shutil.which(cmd[0]):
            return cmd
        raise BuildError(f"the C compiler given by $CC ({cc!r}) was not found")
    for name in ("cc", "gcc", "clang"):
        path = shutil.which(name)
        if path:
            return [path]
    raise BuildError(
        "no C compiler was found (looked for $CC, cc, gcc, clang); the plant FMU is built from C "
        "sources on first use: install one, e.g. `sudo apt-get install build-essential` (Debian/Ubuntu), "
        "`sudo dnf install gcc` (Fedora), `xcode-select --install` (macOS), or set CC=/path/to/compiler")


def config_h(n_bodies: int, fmi_version: int = 2) -> str:
    n = check_n_bodies(n_bodies)
    return (
        "/* generated by plant_fmu/build.py */\n"
        "#ifndef SE3SYNC_CONFIG_H\n#define SE3SYNC_CONFIG_H\n"
        f"#ifndef N_BODIES\n#define N_BODIES {n}\n#endif\n"
        f'#ifndef FMU_GUID\n#define FMU_GUID "{guid(n, fmi_version)}"\n#endif\n'
        "#endif\n"
    )


def quoteattr(text: str) -> str:
    """An XML attribute value, quoted. xml.sax.saxutils is imported here, not at the top: it
    pulls in urllib.request, http.client and ssl (10 ms), and only a build needs it."""
    from xml.sax.saxutils import quoteattr as quote
    return quote(text)


def _fmt(x: float) -> str:
    return repr(float(x))


def model_description_xml(n_bodies: int, fmi_version: int = 2) -> str:
    """modelDescription.xml (FMI 2.0 or 3.0, Co-Simulation) of the plant with ``n_bodies`` bodies."""
    n = check_n_bodies(n_bodies)
    if check_fmi_version(fmi_version) == 3:
        return _model_description_xml3(n)
    out = [
        '<?xml version="1.0" encoding="UTF-8"?>\n',
        '<fmiModelDescription fmiVersion="2.0" modelName="se3sync_plant"',
        f' guid="{guid(n)}"',
        f' description={quoteattr(f"{n} rigid bodies on SE(3), RKMK4 Lie-group integrator")}',
        ' generationTool="se3sync plant_fmu/build.py" variableNamingConvention="structured"',
        ' numberOfEventIndicators="0">\n',
        f'  <CoSimulation modelIdentifier="{MODEL_IDENTIFIER}" needsExecutionTool="false"',
        ' canHandleVariableCommunicationStepSize="true" canInterpolateInputs="false"',
        ' maxOutputDerivativeOrder="0" canRunAsynchronuously="false"',
        ' canBeInstantiatedOnlyOncePerProcess="false" canNotUseMemoryManagementFunctions="true"',
        ' canGetAndSetFMUstate="true" canSerializeFMUstate="true" providesDirectionalDerivative="false">\n',
        "    <SourceFiles>\n",
    ]
    out += [f'      <File name="{f}"/>\n' for f in C_SOURCES]
    out += ["    </SourceFiles>\n", "  </CoSimulation>\n"]
    out += _units_and_categories("fmi2")
    out += ['  <DefaultExperiment startTime="0.0" stopTime="1.0" stepSize="0.001"/>\n',
            "  <ModelVariables>\n"]
    outputs = []
    for index, v in enumerate(layout.variables(n), start=1):
        attrs = (f'name="{v["name"]}" valueReference="{v["vr"]}" description={quoteattr(v["description"])}'
                 f' causality="{v["causality"]}" variability="{v["variability"]}"')
        if v["initial"]:
            attrs += f' initial="{v["initial"]}"'
        real = "<Real"
        if v["unit"]:
            real += f' unit="{v["unit"]}"'
        if v["start"] is not None:
            real += f' start="{_fmt(v["start"])}"'
        out.append(f"    <ScalarVariable {attrs}>{real}/></ScalarVariable>\n")
        if v["causality"] == "output":
            outputs.append(index)
    out += ["  </ModelVariables>\n", "  <ModelStructure>\n", "    <Outputs>\n"]
    out += [f'      <Unknown index="{i}"/>\n' for i in outputs]
    out += ["    </Outputs>\n", "    <InitialUnknowns>\n"]
    out += [f'      <Unknown index="{i}"/>\n' for i in outputs]
    out += ["    </InitialUnknowns>\n", "  </ModelStructure>\n", "</fmiModelDescription>\n"]
    return "".join(out)


def _units_and_categories(status_prefix: str) -> list[str]:
    out = ["  <UnitDefinitions>\n"]
    for name, exps in UNITS.items():
        attrs = " ".join(f'{k}="{v}"' for k, v in exps.items())
        out.append(f'    <Unit name="{name}"><BaseUnit {attrs}/></Unit>\n')
    out += ["  </UnitDefinitions>\n", "  <LogCategories>\n"]
    out += [f'    <Category name="{c}" description={quoteattr(d.replace("fmi2", status_prefix))}/>\n'
            for c, d in LOG_CATEGORIES]
    out += ["  </LogCategories>\n"]
    return out


def _model_description_xml3(n: int) -> str:
    """modelDescription.xml (FMI 3.0, Co-Simulation): same variables, value references,
    causalities, variabilities, start values and units as the FMI 2.0 description, plus the
    independent variable ``time`` (value reference 0) that FMI 3.0 requires."""
    out = [
        '<?xml version="1.0" encoding="UTF-8"?>\n',
        '<fmiModelDescription fmiVersion="3.0" modelName="se3sync_plant"',
        f' instantiationToken="{guid(n, 3)}"',
        f' description={quoteattr(f"{n} rigid bodies on SE(3), RKMK4 Lie-group integrator")}',
        ' generationTool="se3sync plant_fmu/build.py" variableNamingConvention="structured">\n',
        f'  <CoSimulation modelIdentifier="{MODEL_IDENTIFIER}" needsExecutionTool="false"',
        ' canBeInstantiatedOnlyOncePerProcess="false" canGetAndSetFMUState="true" canSerializeFMUState="true"',
        ' providesDirectionalDerivatives="false" providesAdjointDerivatives="false"',
        ' providesPerElementDependencies="false" canHandleVariableCommunicationStepSize="true"',
        ' maxOutputDerivativeOrder="0" providesIntermediateUpdate="false" mightReturnEarlyFromDoStep="false"',
        ' canReturnEarlyAfterIntermediateUpdate="false" hasEventMode="false"',
        ' providesEvaluateDiscreteStates="false"/>\n',
    ]
    out += _units_and_categories("fmi3")
    out += ['  <DefaultExperiment startTime="0.0" stopTime="1.0" stepSize="0.001"/>\n',
            "  <ModelVariables>\n",
            f'    <Float64 name="time" valueReference="{VR_TIME}" description="simulation time"'
            ' causality="independent" variability="continuous" unit="s"/>\n']
    outputs = []
    for v in layout.variables(n):
        attrs = (f'name="{v["name"]}" valueReference="{v["vr"]}" description={quoteattr(v["description"])}'
                 f' causality="{v["causality"]}" variability="{v["variability"]}"')
        if v["initial"]:
            attrs += f' initial="{v["initial"]}"'
        if v["unit"]:
            attrs += f' unit="{v["unit"]}"'
        if v["start"] is not None:
            attrs += f' start="{_fmt(v["start"])}"'
        out.append(f"    <Float64 {attrs}/>\n")
        if v["causality"] == "output":
            outputs.append(v["vr"])
    out += ["  </ModelVariables>\n", "  <ModelStructure>\n"]
    out += [f'    <Output valueReference="{vr}"/>\n' for vr in outputs]
    out += [f'    <InitialUnknown valueReference="{vr}"/>\n' for vr in outputs]
    out += ["  </ModelStructure>\n", "</fmiModelDescription>\n"]
    return "".join(out)


def build_description_xml() -> str:
    """sources/buildDescription.xml (FMI 3.0): how importers (e.g. `fmpy compile`) rebuild the binary."""
    out = [
        '<?xml version="1.0" encoding="UTF-8"?>\n',
        '<fmiBuildDescription fmiVersion="3.0">\n',
        f'  <BuildConfiguration modelIdentifier="{MODEL_IDENTIFIER}"'
        ' description="N_BODIES and FMU_GUID (the instantiationToken) come from config.h">\n',
        '    <SourceFileSet language="C99" compilerOptions="-ffp-contract=off">\n',
    ]
    out += [f'      <SourceFile name="{f}"/>\n' for f in C_SOURCES_FMI3]
    out += ['    </SourceFileSet>\n',
            '    <Library name="m" external="true" description="C math library (libm)"/>\n',
            "  </BuildConfiguration>\n", "</fmiBuildDescription>\n"]
    return "".join(out)


def _compile(n: int, src: Path, lib: Path, fmi_version: int = 2) -> None:
    cmd = find_compiler() + list(CFLAGS) + [f"-DN_BODIES={n}", f"-I{src}"]
    cmd += [str(src / f) for f in _sources(fmi_version)[0]] + ["-o", str(lib), "-lm"]
    try:
        res = subprocess.run(cmd, capture_output=True, text=True)
    except OSError as exc:
        raise BuildError(f"could not run the C compiler {cmd[0]!r}: {exc}") from None
    if res.returncode != 0:
        msg = (res.stderr or res.stdout).strip().replace("\n", " | ")
        raise BuildError(f"compiling the plant FMU failed ({' '.join(cmd)}): {msg[:2000]}")


def build_fmu(n_bodies: int, out, fmi_version: int = 2) -> Path:
    """Builds the FMU (FMI 2.0 or 3.0) for ``n_bodies`` bodies and writes it to ``out`` (atomically)."""
    n = check_n_bodies(n_bodies)
    v = check_fmi_version(fmi_version)
    sources, headers = _sources(v)
    bin_name = binaries_folder(v)
    out = Path(out)
    out_dir = out.parent if str(out.parent) else Path(".")
    if not out_dir.is_dir():
        raise BuildError(f"cannot write {out}: directory {out_dir} does not exist")
    with tempfile.TemporaryDirectory(prefix="se3sync-fmu-") as tmp:
        tmp = Path(tmp)
        src = tmp / "sources"
        src.mkdir()
        for f in sources + headers:
            shutil.copyfile(C_DIR / f, src / f)
        (src / "config.h").write_text(config_h(n, v))
        if v == 3:
            (src / "buildDescription.xml").write_text(build_description_xml())
        bin_dir = tmp / "binaries" / bin_name
        bin_dir.mkdir(parents=True)
        lib = bin_dir / (MODEL_IDENTIFIER + _shared_library_suffix())
        _compile(n, src, lib, v)
        xml = model_description_xml(n, v)
        try:
            fd, part = tempfile.mkstemp(prefix=f".{out.name}.", suffix=".part", dir=out_dir)
        except OSError as exc:
            raise BuildError(f"cannot write {out}: {exc.strerror or exc}") from None
        try:
            with os.fdopen(fd, "wb") as fh, zipfile.ZipFile(fh, "w", zipfile.ZIP_DEFLATED) as z:
                z.writestr("modelDescription.xml", xml)
                z.write(lib, f"binaries/{bin_name}/{lib.name}")
                for f in sorted(src.iterdir()):
                    z.write(f, f"sources/{f.name}")
            os.chmod(part, 0o644)
            os.replace(part, out)
        except BaseException as exc:
            try:
                os.unlink(part)
            except OSError:
                pass
            if isinstance(exc, OSError):
                raise BuildError(f"cannot write {out}: {exc.strerror or exc}") from None
            raise
    return out


def cache_dir() -> Path:
    return Path(os.environ.get("SE3SYNC_CACHE") or "~/.cache/se3sync/fmu").expanduser()


def fmu_path(n_bodies: int, fmi_version: int = 2) -> Path:
    """The cached FMU (FMI 2.0 or 3.0) for ``n_bodies`` bodies, built on first use."""
    n = check_n_bodies(n_bodies)
    v = check_fmi_version(fmi_version)
    d = cache_dir()
    if v == 2:
        key = hashlib.sha256(f"{source_hash()}:{n}:{platform_tag()}".encode()).hexdigest()[:20]
        path = d / f"{MODEL_IDENTIFIER}_n{n}_{platform_tag()}_{key}.fmu"
    else:
        key = hashlib.sha256(f"{source_hash()}:{n}:{platform_tuple()}:fmi3".encode()).hexdigest()[:20]
        path = d / f"{MODEL_IDENTIFIER}_fmi3_n{n}_{platform_tuple()}_{key}.fmu"
    with _lock:
        memo = _memo.get((n, v, str(path)))
        if memo is not None and memo.exists():
            return memo
        if not path.exists():
            try:
                d.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise BuildError(f"cannot create the FMU cache directory {d}: {exc.strerror or exc}") from None
            build_fmu(n, path, v)
        _memo[(n, v, str(path))] = path
        return path
