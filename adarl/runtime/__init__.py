"""The recipe runtime: a recipe (YAML) becomes a run folder with metrics, checkpoints, evaluations and a report.

* :mod:`~adarl.runtime.config` - the recipe schema, loader and dumper;
* :mod:`~adarl.runtime.families` - the one dispatcher: the family an algorithm's base names (its builder and loop);
* :mod:`~adarl.runtime.builders` - where a recipe becomes objects (networks, losses, components);
* :mod:`~adarl.runtime.update` - the update step (TorchRL's SAC step or the fused one; TD3's delayed actor step);
* :mod:`~adarl.runtime.rank_events` - what a rank event sets off, in one place;
* :mod:`~adarl.runtime.trainers` - the training loops on one base: SAC, TD3 and DDPG (off-policy), PPO;
* :mod:`~adarl.runtime.run_folder.run_dir` - the run folder (lock, logs, checkpoints, records);
  :mod:`~adarl.runtime.run_folder.results`
  the same at an fsspec URL;
* :mod:`~adarl.runtime.guards`, :mod:`~adarl.runtime.signals`, :mod:`~adarl.runtime.state` - divergence guards,
  graceful interrupts, RNG and collector state;
* :mod:`~adarl.runtime.evaluation`, :mod:`~adarl.runtime.report`, :mod:`~adarl.runtime.metrics` - evaluation on
  the nominal dynamics, a run's report, metric names;
* :mod:`~adarl.runtime.policy`, :mod:`~adarl.runtime.play` - a trained policy without its run, and watching it.
"""
