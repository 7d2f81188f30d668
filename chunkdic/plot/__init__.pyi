from .mechplots import plot_gauge, plot_profile
from .report import report
