"""Export a bundle for a flight stack or a microcontroller: python scripts/export.py model=D/compensator format=px4 output=F.params."""
import sys
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from gyronet.errors import ConfigError

sys.path.insert(0, str(Path(__file__).resolve().parent))  # scripts/_cli.py, also when this file is run by path
from _cli import CONF_DIR, command  # noqa: E402

FORMATS = ("px4", "ardupilot", "c")
FITS = (None, "px4", "difference")
C_ONLY = ("prefix",)
EXPORT_YAML = CONF_DIR / "deploy" / "export.yaml"
PARAMS_ONLY = ("vehicle_id", "component_id", "grid_points", "temp_rate_c_per_s", "fit", "history")


@command("export", "deploy", schemas={"instance": int, "device_id": int, "vehicle_id": int, "component_id": int,
                            "grid_points": int, "temp_rate_c_per_s": float, "history": str | None, "fit": str | None,
                            "prefix": str},
         required=("model", "output"))
def main(cfg: DictConfig) -> None:
    if not str(cfg.output).strip():  # format=c wrote its files into the working directory
        raise ConfigError("output is empty: give output=F.params, or a folder for format=c (output=c/)")
    if cfg.format not in FORMATS:
        raise ConfigError(f"format must be one of {', '.join(FORMATS)}, got {cfg.format!r}")
    if cfg.get("fit") not in FITS:  # before the heavy imports, as gyronet.deploy.params.FORMS
        raise ConfigError(f"fit must be one of px4, difference (or null: the stack's own), got {cfg.fit!r}")
    if cfg.device_id and cfg.format != "px4":
        raise ConfigError(f"device_id is PX4's TC_G{{n}}_ID; format={cfg.format} takes none"
                          + (" (ArduPilot matches its IMU by instance)" if cfg.format == "ardupilot" else ""))
    if cfg.format == "ardupilot" and cfg.temp_rate_c_per_s != OmegaConf.load(EXPORT_YAML).temp_rate_c_per_s:
        raise ConfigError("temp_rate_c_per_s sets PX4's stated error (its 1 Hz / 1 degC schedule); ArduPilot applies "
                          "its cubic every sample: drop it, or give history=F.csv for the error on a recording")
    if cfg.format == "c" and cfg.instance:
        raise ConfigError("instance picks PX4's or ArduPilot's IMU; for C, give each IMU's compensator its own "
                          "prefix= (prefix=imu1: imu1_step, imu1_compensator.h)")
    defaults = OmegaConf.load(EXPORT_YAML)
    ignored = [key for key in (C_ONLY if cfg.format != "c" else PARAMS_ONLY) if cfg.get(key) != defaults.get(key)]
    if ignored:  # an option of the other kind of export would be silently ignored
        kind = "format=c" if cfg.format != "c" else "the .params formats (px4, ardupilot)"
        raise ConfigError(f"{', '.join(ignored)}: {'an option' if len(ignored) == 1 else 'options'} of {kind}, "
                          f"not of format={cfg.format}")
    if cfg.format == "c":
        try:
            from gyronet.deploy.c_export import write_c
        except ModuleNotFoundError as err:
            if err.name != "gyronet.deploy.c_export":
                raise
            raise ConfigError("format=c needs gyronet.deploy.c_export, which this install lacks") from None
        summary = write_c(Path(cfg.model), Path(cfg.output), cfg.prefix)
        print("\n".join(f"{key}: {value}" for key, value in summary.items()))
        return
    from gyronet.deploy.params import export_params

    summary = export_params(cfg.model, cfg.output, cfg.format, cfg.instance, cfg.device_id, cfg.vehicle_id,
                            cfg.component_id, cfg.grid_points, float(cfg.temp_rate_c_per_s), cfg.get("history"),
                            cfg.get("fit"))

    def axes(errors: dict) -> str:
        return ", ".join(f"{axis}={errors[axis]:.3g}" for axis in "xyz")

    users = ("as PX4's firmware runs it (1 Hz, 1 degC)" if cfg.format == "px4"
             else "e(T) - e(T_cal) after ArduPilot's boot calibration")
    print(f"{summary['params']}: {summary['n_params']} parameters; cubic over {summary['temp_min_c']:.3f} .. "
          f"{summary['temp_max_c']:.3f} degC, largest error against the bundle's curve {axes(summary['max_error_dps'])} "
          f"deg/s per sample, {axes(summary['stated_error_dps'])} deg/s {users} "
          f"(at dT/dt = 0; {Path(summary['params']).with_suffix('.json')})")

if __name__ == "__main__":
    main()
