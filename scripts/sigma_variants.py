import sys, json, numpy as np, torch
from omegaconf import OmegaConf
from hydra.utils import instantiate
from gyronet.sim import simulate, write_simulation
from gyronet.dataset import DriftData
from gyronet.pipeline import train_run
from gyronet import error_bar_fit as ebf
from gyronet.compensator import Compensator
from gyronet.data import load_recording, load_truth
from gyronet.sigma_table import block_coverage
root='/tmp/eb/cal'
cfg=OmegaConf.load('conf/model/default.yaml')
results={}
for sensor in [int(a) for a in sys.argv[1:]]:
    tp=f'{root}/p{sensor}.csv'
    write_simulation(simulate("paper", fs_hz=2.0, seed=1, sensor_seed=sensor), tp)
    data=DriftData(tp)
    model=instantiate(cfg, n_inputs=data.n_features)
    train_run(data, model, None, f'{root}/run{sensor}', {"progress": False, "for_bundle": True})
    stats=model.__dict__[ebf.STATS_ATTR]; parts=model.__dict__[ebf.MEMBERS_ATTR]
    x_fit=np.concatenate([data.train.x,data.val.x])
    comp=Compensator.load(f'{root}/run{sensor}/compensator')
    for prof,seed in (("random",5),("cycle",6)):
        hp=f'{root}/{prof}{sensor}.csv'
        write_simulation(simulate(prof, fs_hz=2.0, seed=seed, sensor_seed=sensor), hp)
        rec=load_recording(hp); tr=load_truth(hp).columns
        comp.reset(); out=comp.process(rec.columns)
        comp.reset(); feats=comp.extractor.process(rec.columns)
        err=out.drift_dps-np.column_stack([tr[f"drift_{a}_dps"] for a in "xyz"])
        for share in (0.0,0.05,0.1,0.2,0.3):
            bar=ebf.shape_of(model, parts, x_fit)
            lo,hi=ebf.edge_slopes(model,x_fit,ebf.box_of(model,x_fit),share)
            bar.slope_low_dps,bar.slope_high_dps=lo,hi
            sp=bar.spread(feats); o=bar.outside_dps(feats)
            for rule in ("mle","scale1","floor_rms"):
                st=dict(stats)
                if rule=="mle":
                    f,k,_=ebf.calibrate(st)
                elif rule=="scale1":
                    # floor by ML with the spread scale fixed at 1
                    r2=st["residual"]**2; f=np.zeros(3); k=np.ones(3)
                    for a in range(3):
                        rms=np.sqrt(r2[:,a].mean()); g=np.geomspace(1e-3,3,200)*rms
                        var=g[:,None]**2+st["spread"][None,:,a]**2+st["outside"][None,:,a]**2+st["noise_var"][a]
                        f[a]=g[np.argmin(np.sum(np.log(var)+r2[None,:,a]/var,1))]
                else:
                    k=np.zeros(3); f=np.sqrt(np.maximum((st["residual"]**2).mean(0)-st["noise_var"],1e-12))
                sig=np.sqrt(f**2+(k*sp)**2+o**2)
                s=block_coverage(rec.time_s,err,sig,out.out_of_range)
                results.setdefault(f"{rule} share={share}",[]).append([s["within_1_sigma"][a] for a in "xyz"])
        print(sensor,prof,flush=True)
for k,v in results.items():
    v=np.array(v); print(k, v.round(2).tolist(), "mean %.2f"%v.mean())
