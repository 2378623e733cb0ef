"""Workflows that combine training, run directories, proofs, simulation and figures (what the commands run):

* :mod:`~drlyap.workflows.verify` -- proving what a run directory holds;
* :mod:`~drlyap.workflows.record` -- what a verification leaves in it: metrics.json's account, the certificates;
* :mod:`~drlyap.workflows.reproduce` -- the paper's experiment, baseline against DR;
* :mod:`~drlyap.workflows.compare` -- runs of any kind side by side;
* :mod:`~drlyap.workflows.guarantee` -- the probability behind the paper's lemma;
* :mod:`~drlyap.workflows.plot` -- the figures of one run;
* :mod:`~drlyap.workflows.sweep` -- grids of seeds, radii and risk levels, resumable, locally or on Ray.
"""
