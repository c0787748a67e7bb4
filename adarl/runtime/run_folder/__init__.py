"""A run folder: what ``adarl run`` writes and every other command reads, each concern in its own module.

- :mod:`~adarl.runtime.run_folder.run_dir`: :class:`RunDir`, the folder's layout, its claim and its recipe records;
- ``_records`` (metrics, evaluations, ranks, summary), ``_checkpoints`` (checkpoints and their replay buffers),
  ``_loggers`` (TorchRL's loggers, as one), ``_lock`` (one process trains in a folder), ``_file_safety`` (atomic
  writes, storage errors named): the private parts :class:`RunDir` is made of;
- :mod:`~adarl.runtime.run_folder.results`: run folders at fsspec URLs (copies, mirrors, uploads).

The hub imports nothing: ``results`` is light (what a report reads), ``run_dir`` is not.
"""
