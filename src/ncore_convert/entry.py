"""The ``ncore-convert`` console script. Its first statement routes SIGINT and SIGTERM to
:mod:`ncore_convert.run.stop`, before the command line is parsed and before any worker, fork
server, thread or Ray connection exists: a run stopped at any moment exits 130 and leaves no
process behind."""

from ncore_convert.run import stop

stop.install()


def main() -> None:
    from ncore_convert.cli import main as cli_main

    cli_main()
