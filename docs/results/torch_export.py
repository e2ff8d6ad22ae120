"""Could ``torch.export`` carry a bundle's model instead of TorchScript? Equality, size and speed, side by side.

python docs/results/torch_export.py BUNDLE_DIR   # an RBFNet bundle, e.g. the quick start's (run by hand, not by the build)

Rebuilds the bundle's network in eager PyTorch from ``model.pt``'s weights, exports it with a free batch
size, saves and loads it as ``torch.export`` does, and compares it with the frozen TorchScript that
``read_bundle`` gives: the largest difference, the file's size, and the time a call on 8,192 rows and
on one row (the live path's worst case when it has no floats model).
"""
import io
import sys
import time
import warnings

import torch

from gyronet.bundle.io import LoadedBundle, load_unfrozen, read_bundle
from gyronet.model.rbf import RBFNet


def eager_model(bundle: str, loaded: LoadedBundle) -> RBFNet:
    """The bundle's RBFNet in eager PyTorch, with ``model.pt``'s parameters and buffers (``loaded``: it, read)."""
    config = loaded.meta["model"]
    if config["class"] != "RBFNet":
        sys.exit(f"error: {bundle} holds a {config['class']}, this probe rebuilds an RBFNet only")
    model = RBFNet(loaded.facts.n_inputs, 3, config["n_centers"], rbf_inputs=config["rbf_inputs"],
                   linear=config["use_linear"], temp_degree=config["temp_degree"], clamp=config["clamp"])
    model.load_state_dict(load_unfrozen(bundle).state_dict())
    return model.eval()


def us_per_call(model, x: torch.Tensor, calls: int) -> float:
    """Mean time of one call, in microseconds, after a warm-up call."""
    model(x)
    start = time.perf_counter()
    for _ in range(calls):
        model(x)
    return (time.perf_counter() - start) / calls * 1e6


def main(bundle: str) -> None:
    warnings.simplefilter("ignore")  # torch's deprecation of torch.jit, which this file compares against
    loaded = read_bundle(bundle)
    scripted, model = loaded.model, eager_model(bundle, loaded)
    box = model.x_mean + model.x_std * torch.randn(8192, len(model.x_mean), dtype=torch.float64)
    exported = torch.export.export(model, (box,), dynamic_shapes=({0: torch.export.Dim("rows")},))
    exported_file, script_file = io.BytesIO(), io.BytesIO()
    torch.export.save(exported, exported_file)
    torch.jit.save(torch.jit.script(model), script_file)
    exported_file.seek(0)
    reloaded = torch.export.load(exported_file).module()
    with torch.no_grad():
        print(f"torch {torch.__version__}; largest |export - TorchScript|: "
              f"{(reloaded(box) - scripted(box)).abs().max().item():.3g} deg/s (8,192 rows), "
              f"{(reloaded(box[:1]) - scripted(box[:1])).abs().max().item():.3g} (one row)")
        print(f"file: export {len(exported_file.getvalue()):,} B, TorchScript {len(script_file.getvalue()):,} B")
        for name, run in (("TorchScript (frozen)", scripted), ("export", reloaded)):
            print(f"{name}: {us_per_call(run, box, 50):,.0f} us a call on 8,192 rows, "
                  f"{us_per_call(run, box[:1], 2000):,.1f} us on one row")


if __name__ == "__main__":
    main(sys.argv[1])
