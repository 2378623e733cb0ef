"""The ``drlyap`` command line (click): one module per group of commands, each parsing its options, calling the
library and printing what :mod:`drlyap.render` words. Every command has ``--help``.

* :mod:`~drlyap.cli.train` -- ``systems``, ``train``;
* :mod:`~drlyap.cli.verify` -- ``verify``, ``lipschitz``, ``guarantee``;
* :mod:`~drlyap.cli.evaluate` -- ``evaluate``, ``plot``;
* :mod:`~drlyap.cli.baselines` -- ``lqr``, ``rl train``;
* :mod:`~drlyap.cli.workflows` -- ``reproduce``, ``compare``, ``sweep``;
* :mod:`~drlyap.cli.export` -- ``export``;
* :mod:`~drlyap.cli.check` -- ``check``;
* :mod:`~drlyap.cli.imported` -- ``import``.

The numerical code is imported only when a command runs, so ``drlyap --help`` answers at once.
"""

from __future__ import annotations

import click

from drlyap.cli import baselines, check, evaluate, export, imported, train, verify, workflows
from drlyap.cli.common import setup_threads
from drlyap.cli.startup import announce_slow_loading


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="drlyap")
def main() -> None:
    """Distributionally robust neural controllers with Lyapunov certificates.

    Train a controller pi and Lyapunov function V on an uncertain system from a few samples of its
    parameters, then evaluate the closed loop on the true, shifted system.
    """
    setup_threads()
    announce_slow_loading()


for command in (train.systems, train.train, evaluate.evaluate, workflows.reproduce, baselines.lqr, baselines.rl,
                workflows.compare, verify.verify, verify.guarantee, verify.lipschitz, evaluate.plot, workflows.sweep,
                export.export, check.check, imported.import_pair):
    main.add_command(command)

if __name__ == "__main__":
    main()
