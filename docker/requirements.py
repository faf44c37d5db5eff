"""Print thermofield's requirements from pyproject.toml, one per line, for ``pip install -r`` with constraints.txt.

    python3 requirements.py                 the dependencies of the package
    python3 requirements.py --only gateway  those of the gateway extra alone
    python3 requirements.py --extras        the names of every extra, comma-separated (for `make constraints`)

The image build installs the dependencies before it copies the source, so that the layer holding them is
rebuilt only when pyproject.toml or constraints.txt change. Standard library only: it runs in the bare base image.
"""

import argparse
import tomllib
from pathlib import Path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pyproject", type=Path, default=Path(__file__).with_name("pyproject.toml"))
    choice = parser.add_mutually_exclusive_group()
    choice.add_argument("--only", metavar="EXTRA", help="the requirements of this extra alone")
    choice.add_argument("--extras", action="store_true", help="the names of the extras")
    args = parser.parse_args()
    pyproject = args.pyproject if args.pyproject.exists() else Path(__file__).resolve().parents[1] / "pyproject.toml"
    project = tomllib.loads(pyproject.read_text())["project"]
    extras = project.get("optional-dependencies", {})
    if args.extras:
        print(",".join(extras))
    elif args.only:
        if args.only not in extras:
            raise SystemExit(f"{pyproject}: no extra {args.only!r} (extras: {', '.join(extras)})")
        print("\n".join(extras[args.only]))
    else:
        print("\n".join(project["dependencies"]))


if __name__ == "__main__":
    main()
