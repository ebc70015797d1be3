"""Command line: ``python -m rosidl_build check|build``.

``check`` only parses and resolves the ``.msg`` files (no generator needed); ``build`` also
generates and compiles them into a scratch folder. Both exit with status 1 and a one-line
error on a malformed interface.
"""

import argparse
from pathlib import Path
import sys

from . import build_interfaces, InterfaceError, ros_prefixes, validate_interfaces


def main(argv=None) -> int:
    """Entry point; returns the process exit status."""
    parser = argparse.ArgumentParser(prog='python -m rosidl_build', description=__doc__)
    parser.add_argument('command', choices=('check', 'build'))
    parser.add_argument('--package', default='eha_ros', help='package name (default eha_ros)')
    parser.add_argument('--package-dir', type=Path, default=Path.cwd(),
                        help='package root holding msg/ (default: current folder)')
    parser.add_argument('--build-dir', type=Path, default=Path('build/rosidl'),
                        help='scratch folder for build (default build/rosidl)')
    parser.add_argument('--prefix', action='append', default=[],
                        help='extra install prefix with ROS packages (repeatable)')
    parser.add_argument('msg_files', nargs='*', type=Path,
                        help='.msg files (default: <package-dir>/msg/*.msg)')
    args = parser.parse_args(argv)
    msg_files = args.msg_files or sorted((args.package_dir / 'msg').glob('*.msg'))
    prefixes = ros_prefixes(args.prefix)
    try:
        if args.command == 'check':
            specs, dependencies = validate_interfaces(msg_files, args.package, prefixes)
            for spec in specs:
                print(f'{spec.full_name}: {len(spec.fields)} fields, '
                      f'{len(spec.constants)} constants')
            print(f'dependencies: {", ".join(dependencies) or "none"}')
        else:
            build_interfaces(args.package, args.package_dir, msg_files, args.build_dir,
                             prefixes=prefixes)
    except InterfaceError as exc:
        print(f'error: {exc}', file=sys.stderr)
        return 1
    return 0


if __name__ == '__main__':
    sys.exit(main())
