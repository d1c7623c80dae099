"""laser-calib's exit status for a command line, as a shell sees it: main's return, or
the status argparse exits with after its own one-line errors (bad option values)."""

from laser_calib.cli.main import main


def exit_status(argv: list[str]) -> int:
    try:
        return main(argv)
    except SystemExit as exc:
        return exc.code
