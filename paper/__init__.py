"""The paper's own experiments and the studies' per-run tables, outside the installed
package: run from the repository root as ``python -m paper.<name>``
(``paper.bandit_ablation``, ``paper.risky_detour``, ``paper.compare``)."""
