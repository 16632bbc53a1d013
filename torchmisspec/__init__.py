"""torchmisspec: learn the missing term of a misspecified ODE with a Gaussian process, and design the experiments."""
from . import systems
from ._errors import *  # noqa: F401,F403
from .data import Trajectories, simulate
from .gp import CorrectionGP, GPPosterior
from .systems import MisspecifiedSystem
