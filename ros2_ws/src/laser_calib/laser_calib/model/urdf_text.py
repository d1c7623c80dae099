"""The URDF text of a robot description file: a .urdf (or .xml) read in the encoding its XML
declaration names, a .xacro expanded by the ``xacro`` package with its arguments checked, its
$(find pkg) resolved through the installed packages and ROS_PACKAGE_PATH's (io.ament) and its
failures named at the included file they are in, as a user finds it."""

from __future__ import annotations

import re
from pathlib import Path

from laser_calib.io.ament import in_package, package_index
from laser_calib.io.errors import InputError
from laser_calib.io.read import read_text

_MISSING_PACKAGE = re.compile(r"package '([^']+)' not found")  # ament_index_python's PackageNotFoundError


class _ArgsRead(dict):
    """The xacro arguments given, noting each name xacro asks for: it looks up every <xacro:arg>
    it meets (in the includes too, as it resolves them) and every $(arg) / xacro.arg() it reads
    in this mapping, so a given name it never asked for is one the file ignores."""

    def __init__(self, given: dict[str, str]):
        super().__init__(given)
        self.asked: set[str] = set()

    def __contains__(self, name) -> bool:
        self.asked.add(name)
        return super().__contains__(name)

    def __getitem__(self, name):
        self.asked.add(name)
        return super().__getitem__(name)


class _FileContext(dict):
    """xacro's substitution context, whose ``filename`` is the file xacro is reading at the moment
    (the top of its include stack). $(dirname) reads it there, but the xacro on PyPI (2.1.1) never
    sets it: every $(dirname) failed ('no file/directory information available'), in the top file
    and in includes, while the ROS build of xacro resolves it to the folder of the file it is in."""

    def get(self, key, default=None):
        if key == "filename":
            import xacro

            return (xacro.filestack or [default])[-1]
        return super().get(key, default)

    def __getitem__(self, key):
        return self.get(key) if key == "filename" else super().__getitem__(key)


def urdf_text(path: str | Path, xacro_args: dict[str, str] | None = None, args_where: str | None = None) -> str:
    """The URDF text of a .urdf file, or of a .xacro file after expansion with
    ``xacro_args`` (name -> value, as ``xacro file.xacro name:=value``). An argument the
    xacro neither declares nor reads is refused (xacro ignores it: the default variant
    would be built), named at ``args_where`` (the robot file's key)."""
    path = Path(path)
    if path.suffix.lower() != ".xacro":
        return _xml_text(path)
    prefix = ""  # package_index's, to name the packages' files in a message
    try:
        import xacro  # only for xacro input

        args = _ArgsRead(xacro_args or {})
        if not isinstance(xacro.substitution_args_context, _FileContext):
            xacro.substitution_args_context = _FileContext(xacro.substitution_args_context)
        with package_index() as prefix:  # $(find pkg): installed packages, then ROS_PACKAGE_PATH's
            text = xacro.process_file(str(path), mappings=args).toxml()
    except OSError as exc:
        raise InputError(str(path), f"cannot read ({exc.strerror})") from None
    except Exception as exc:  # xacro raises its own XacroException and XML errors
        missing = _MISSING_PACKAGE.search(str(getattr(exc, "exc", None) or exc))
        if missing:
            raise InputError(str(path), f"xacro: package '{missing[1]}' ($(find {missing[1]})) is not in "
                                        "AMENT_PREFIX_PATH or ROS_PACKAGE_PATH: source the workspace that installs "
                                        "it, or add its source folder to ROS_PACKAGE_PATH") from None
        raise InputError(in_package(_failed_in(path), prefix),
                         f"xacro failed ({in_package(' '.join(str(exc).split()), prefix)})") from None
    unknown = sorted(set(xacro_args or {}) - args.asked)
    if unknown:
        declared = sorted(args.asked)
        raise InputError(args_where or str(path), f"unknown xacro argument{'s' * (len(unknown) > 1)} "
                                                  f"{', '.join(map(repr, unknown))}: {path.name} declares "
                                                  + (', '.join(declared) if declared else "no arguments"))
    return text


def _failed_in(path: Path) -> str:
    """The file xacro was reading when it failed, with the includes that led there: xacro's own
    include stack (a property named __x in an included file was blamed on the top-level one)."""
    import xacro

    stack = [str(name) for name in (getattr(xacro, "filestack", None) or []) if name]
    if len(stack) < 2 or Path(stack[0]) != path:
        return str(path)
    return f"{stack[-1]} (included from {' <- '.join(reversed(stack[:-1]))})"


_DECLARED = re.compile(rb"^(\xef\xbb\xbf)?\s*<\?xml[^>]*?encoding\s*=\s*[\"']([A-Za-z0-9._-]+)[\"']")


def _xml_text(path: Path) -> str:
    """The text of an XML file in the encoding its declaration names (UTF-8 without one), its
    declaration then saying UTF-8: the text is encoded as UTF-8 for the parser, and the
    calibrated URDF written from it is. A URDF in ISO-8859-1 (an author's name in a comment) is
    valid XML, and ROS reads it."""
    declared = _DECLARED.match(path.read_bytes()[:200]) if path.is_file() else None
    encoding = declared[2].decode() if declared else "utf-8"
    if encoding.lower().replace("_", "-") in ("utf-8", "utf8"):
        return read_text(path)
    try:
        text = path.read_bytes().decode(encoding)
    except LookupError:
        raise InputError(str(path), f"its XML declaration names an unknown encoding {encoding!r}") from None
    except UnicodeDecodeError as exc:
        raise InputError(str(path), f"not {encoding} text, as its XML declaration says (byte {exc.start})") from None
    return re.sub(r"""(encoding\s*=\s*["'])[A-Za-z0-9._-]+""", r"\1UTF-8", text, count=1)
