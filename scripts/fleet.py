"""Train one bundle per unit, then tabulate them: python scripts/fleet.py 'data.path=glob(units/*.csv)' [train.py overrides].

Hydra's own ``glob()`` picks among a config group's options, not files: ``train.py -m
'data.path=glob(units/*.csv)'`` launches 0 jobs. This command expands the pattern into units
(gyronet.training.fleet) and runs ``scripts/train.py -m`` with ``+unit=<each unit>``,
``data.path=<folder>/${unit}.csv`` and ``hydra.sweep.subdir=${unit}``. Every other argument is
train.py's (``model=``, ``train.*``, ``hydra/launcher=joblib|submitit_local|submitit_slurm``,
``hydra.launcher.*``, ``hydra.sweep.dir=S``), except ``fleet.spec_range_c=[LOW,HIGH]``, the
temperature range every unit must cover. When the launcher returns, ``S/fleet_table.md`` and
``S/fleet_table.json`` hold every unit's figures (``scripts/fleet_table.py sweep=S`` tabulates again).
"""
import datetime
import json
import re
import sys
from pathlib import Path

from gyronet.errors import EXIT_BAD_INPUT, GyronetError, exit_on_error
from gyronet.training.fleet import check_spec_range, find_units, fleet_table, sweep_overrides, write_table, write_units

SCRIPTS = Path(__file__).resolve().parent
TABLE = "fleet_table.md"
_GLOB = re.compile(r"data\.path=glob\((.+)\)\Z")
_USAGE = "python scripts/fleet.py 'data.path=glob(units/*.csv)' [train.py overrides]"


def parse(argv: list[str]) -> tuple[str, list[float] | None, str | None, list[str]]:
    """The file pattern, the spec range, the sweep folder if given, and train.py's own arguments."""
    pattern, spec, sweep_dir, rest = None, None, None, []
    for arg in argv:
        found = _GLOB.match(arg)
        if found:
            pattern = found.group(1).strip().strip("'\"")
        elif arg.startswith(("data.path=", "data.paths=")):
            raise GyronetError(f"{arg}: a fleet takes its units as data.path=glob(PATTERN): {_USAGE}")
        elif arg.startswith("fleet.spec_range_c="):
            spec = _range(arg.split("=", 1)[1])
        elif arg.startswith("fleet."):
            raise GyronetError(f"unknown setting {arg.split('=', 1)[0]}; the fleet settings are fleet.spec_range_c")
        elif arg not in ("-m", "--multirun"):  # always a multirun
            if arg.startswith("hydra.sweep.dir="):
                sweep_dir = arg.split("=", 1)[1]
            rest.append(arg)
    if pattern is None:
        raise GyronetError(f"no units given: {_USAGE}")
    return pattern, spec, sweep_dir, rest


def _range(text: str) -> list[float]:
    try:
        value = json.loads(text)
    except ValueError:
        value = text
    return check_spec_range(value, "fleet.spec_range_c")


@exit_on_error
def main() -> None:
    pattern, spec_range_c, sweep_dir, rest = parse(sys.argv[1:])
    units, root, suffix = find_units(pattern)
    if sweep_dir is None:
        sweep_dir = f"outputs/fleet/{datetime.datetime.now():%Y-%m-%d_%H-%M-%S}"
        rest.append(f"hydra.sweep.dir={sweep_dir}")
    write_units(sweep_dir, units)
    sys.path.insert(0, str(SCRIPTS))
    import train  # noqa: E402 -- scripts/train.py, whose Hydra app runs each unit

    # each job first sets its unit's earlier outputs aside: a re-run that fails is not listed with the old bundle
    callback = "+hydra.callbacks.fleet_outputs._target_=_cli.SetAsideEarlierOutputs"
    sys.argv = [str(SCRIPTS / "train.py"), "-m", *sweep_overrides(units, root, suffix), callback, *rest]
    status = 0
    try:
        train.main()
    except SystemExit as stop:  # a failed unit: its error is already on stderr; tabulate the others
        status = stop.code if isinstance(stop.code, int) else EXIT_BAD_INPUT
    if status and not any((Path(sweep_dir) / unit).is_dir() for unit in units):  # refused before any unit ran
        raise SystemExit(status)
    table = fleet_table(sweep_dir, spec_range_c)
    output = write_table(table, Path(sweep_dir) / TABLE)
    print(f"fleet: {table['n_ok']} of {table['n_units']} units trained; table {output} (and .json)", file=sys.stderr)
    if status:
        raise SystemExit(status)


if __name__ == "__main__":
    main()
