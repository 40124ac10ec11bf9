"""Close the loop with measured data: find the residual, trace it to an effect, add it, report.

The thesis stops at PLF+ and lists the suspects for what remains (Sec. 2.2.2, 6.6, 7.3). This
package turns that list into a tool:

* :mod:`.effects`: the effect library, each a physically named augmentation of a base model;
* :mod:`.structure`: a base model plus effects as one separable least-squares problem (linear
  parameters by least squares, nonlinear ones by ``scipy.optimize``);
* :mod:`.evidence`: held-out improvement, BIC, an F test and identifiability of one candidate;
* :mod:`.diagnosis`: rank the candidates, add the best while the evidence holds, and say what
  structure remains that no family explains;
* :mod:`.model`: the augmented model, an ordinary model file the runtime can run in the loop;
* :mod:`.learned`: ``--learned``, what the named effects leave learned by a PENN and an NNN, and
  whether it is conservative (needs the extra ``nn``);
* :mod:`.report`: ``summary.json`` (docs/residual.md), a readable report and its plots.
"""
