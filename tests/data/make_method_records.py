"""Writes tests/data/model_critic_records.npz: gp_model's and gp_critic's records on the tiny
preset and on every standard preset, 2 seeds (0, 1; the double pendulum 0 only), 2 updates (the
double pendulum 1), float64, as `gpguided reproduce` runs them (`reproduce.reproduce`).
tests/test_method_records.py checks the library against it.

    python tests/data/make_method_records.py [--presets ...]

With --presets, only those presets' records are rewritten (a preset whose settings changed).
"""

import argparse
import os
import tempfile

import numpy as np

import gpguided_jax
from gpguided_jax import reproduce, runtime

PRESETS = ("tiny", "swingup", "pendulum-v1", "mountaincar-continuous", "inverted-pendulum",
           "inverted-double-pendulum")
METHODS = ("gp_model", "gp_critic")
SEEDS = (0, 1)
# fewer seeds and updates where one run costs minutes (the double pendulum's gp_model)
SEEDS_OF = {"inverted-double-pendulum": (0,)}
NUM_UPDATES = 2
UPDATES_OF = {"inverted-double-pendulum": 1}
OUT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "model_critic_records.npz")


def records(preset: str) -> dict[str, np.ndarray]:
    """`preset/method/field` -> (seeds, updates) for METHODS on `preset`."""
    with tempfile.TemporaryDirectory() as out_dir:
        updates = UPDATES_OF.get(preset, NUM_UPDATES)
        reproduce.reproduce(preset, SEEDS_OF.get(preset, SEEDS), METHODS, out_dir,
                            dtype="float64", chunk_size=updates,
                            overrides={"num_updates": updates}, progress=lambda _: None)
        with np.load(os.path.join(out_dir, "results.npz")) as res:
            names = [str(m) for m in res["methods"]]
            skip = {"methods", "seeds", "num_updates", "env_steps"}
            return {f"{preset}/{m}/{k}": res[k][i] for k in res.files if k not in skip
                    for i, m in enumerate(names) if not np.all(np.isnan(res[k][i]))}


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--presets", nargs="+", default=list(PRESETS))
    args = parser.parse_args()
    runtime.single_threaded_lapack()
    gpguided_jax.enable_x64()
    out = {}
    if os.path.exists(OUT):  # the presets not asked for keep their records
        with np.load(OUT) as old:
            out = {k: old[k] for k in old.files if k.split("/")[0] not in args.presets}
    for p in args.presets:
        print(p, flush=True)
        out.update(records(p))
    np.savez_compressed(OUT, **out)
    print(f"wrote {OUT}: {len(out)} arrays")


if __name__ == "__main__":
    main()
