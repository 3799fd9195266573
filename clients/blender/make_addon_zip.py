"""Package the add-on as the zip a user installs from Blender (Preferences > Add-ons > Install).

Run from anywhere: ``python3 clients/blender/make_addon_zip.py`` writes
``clients/blender/dist/complementme_blender.zip`` (or ``--out FILE``) and prints its path. The
zip holds the ``complementme_blender/`` folder with its Python files only, with fixed
timestamps, so that the same sources give the same bytes.
"""

from __future__ import annotations

import argparse
import zipfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
PACKAGE = HERE / "complementme_blender"
DEFAULT_OUT = HERE / "dist" / "complementme_blender.zip"
FIXED_TIME = (2024, 1, 1, 0, 0, 0)


def build(out: Path = DEFAULT_OUT) -> Path:
    """Write the add-on zip to ``out`` and return it."""
    out.parent.mkdir(parents=True, exist_ok=True)
    files = sorted(PACKAGE.glob("*.py"))
    assert files, f"no add-on sources under {PACKAGE}"
    with zipfile.ZipFile(out, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for path in files:
            info = zipfile.ZipInfo(f"{PACKAGE.name}/{path.name}", date_time=FIXED_TIME)
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            zf.writestr(info, path.read_bytes())
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help="Where to write the zip.")
    print(build(parser.parse_args().out))


if __name__ == "__main__":
    main()
