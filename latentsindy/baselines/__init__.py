"""The methods dynamic SINDy is compared with in the seed paper (section 4.6).

* :class:`WindowedSINDy`: SINDy on windows with one sparsity pattern across them
  (group hard thresholding, or thresholding of window-averaged coefficients).
* :func:`switching_lds`: AR-HMM, SLDS and rSLDS segmentations through ``ssm`` (an
  optional extra; see :func:`import_ssm` for the install steps).
"""

from ._slds import Segmentation, import_ssm, switch_time_errors, switching_lds
from ._windowed import WindowedSINDy

__all__ = ["WindowedSINDy", "switching_lds", "Segmentation", "switch_time_errors",
           "import_ssm"]
