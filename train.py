"""Train WCSAC or a baseline: ``python train.py algo=wcsac risk_level=0.5 env=dynamic``.

The card's entry point in a checkout; the same code as the installed ``wcsac-train``
and ``python -m wcsac_rl.train`` (:mod:`wcsac_rl.train`: its docstring says the rest).
Hydra composes ``conf/config.yaml``; with no overrides this is the paper's full run.
Sweeps: ``python train.py -m algo=wcsac risk_level=0.1,0.5,0.9 seed=0,10,20``; on a
cluster: ``python train.py -m experiment=table1_static hydra/launcher=slurm`` (docs/reproduce.md,
"Run the paper's sweeps on a cluster").
"""

from wcsac_rl.train import check_command_line, check_output_dirs, cli, main

__all__ = ["check_command_line", "check_output_dirs", "cli", "main"]

if __name__ == "__main__":
    cli()
