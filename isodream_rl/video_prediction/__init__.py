"""Action-conditioned video prediction (Iso-Dream Sec. 4.4): ST-LSTM cells, the three-branch
predictor and its variants, the objective, per-frame PSNR/SSIM, training and the ``isodream-video`` CLI."""

from isodream_rl.video_prediction.config import VARIANTS, PredictorConfig, variant_config
from isodream_rl.video_prediction.inverse_dynamics import ActionInverseCell
from isodream_rl.video_prediction.metrics import FrameMetrics
from isodream_rl.video_prediction.objective import VideoPredictionLoss
from isodream_rl.video_prediction.predictor import ThreeBranchPredictor
from isodream_rl.video_prediction.st_lstm import ActionConditionedSTLSTMCell, SpatioTemporalLSTMCell

__all__ = [
    "VARIANTS",
    "ActionConditionedSTLSTMCell",
    "FrameMetrics",
    "ActionInverseCell",
    "PredictorConfig",
    "SpatioTemporalLSTMCell",
    "ThreeBranchPredictor",
    "VideoPredictionLoss",
    "variant_config",
]
