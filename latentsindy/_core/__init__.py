"""The shared numerical core: what both stages, the baselines and the C. elegans
workflow use, and nothing that knows about either stage.

* ``validation``: checks on user input, done once at the boundary;
* ``recordings``: recordings cut at missing rows and gaps into segments (``DataUse``);
* ``local_fits``: local polynomial fits on the actual sample times (any spacing);
* ``derivatives``: noise-adaptive differentiation and the derivative noise level;
* ``library``: pysindy feature libraries, evaluated and named, as sympy expressions;
* ``shapes``: coefficient shapes over time (re-exported by ``latentsindy.systems``);
* ``symbolic``: a closed system's sympy right-hand side as a numpy/torch callable;
* ``simulate``: integration with a finite step budget, blow-ups reported;
* ``figures``: matplotlib on demand and saving figures;
* ``saving``: the hook through which result types are written by ``latentsindy._files``;
* ``timing``: wall time by stage (a discovery's ``timings``);
* ``threads``: one thread for torch and the BLAS on small arrays;
* ``parallel``: independent pieces of one discovery shared with a forked helper process.
"""
