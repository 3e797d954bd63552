"""Training configuration: one dataclass, saved inside every checkpoint."""

from __future__ import annotations

import argparse
from dataclasses import asdict, dataclass, field, fields

from training.losses import LossWeights
from training.networks.posenet import GATE_WIDTH

STAGES = ("rigid", "flow")
ARCHS = ("resnet50", "vgg", "small")
AMP_MODES = ("off", "bf16", "fp16")


@dataclass
class TrainConfig:
    stage: str = "rigid"
    arch: str = "resnet50"
    data_dir: str = "data/prepared"
    extra_data_dirs: list[str] = field(default_factory=list)  # more prepared folders mixed into train
    out_dir: str = "runs/rigid"
    init_checkpoint: str | None = None  # weights to start from (rigid: fine-tune; flow: freeze depth/pose)
    resume: str | None = None  # checkpoint of this stage to continue exactly
    seq_length: int = 3
    height: int = 128
    width: int = 416
    batch_size: int = 4
    lr: float = 2e-4
    beta1: float = 0.9
    beta2: float = 0.999
    max_steps: int = 1000
    max_minutes: float | None = None  # wall-clock budget; stops early and saves
    seed: int = 8964
    num_workers: int = 2
    augment: bool = True
    share_color_gain: bool = False
    freeze_depth: bool = False  # stage rigid: train PoseNet alone, DepthNet kept as initialised
    gate_only: bool = False  # stage rigid: train PoseNet's motion gate alone (--pose-gate)
    rigid_corruption: float = 1.0  # stage flow: poses behind ResFlowNet's rigid input scaled in [1/c, c]
    hard_gate: bool = False  # with --pose-gate: outside training the gate is a step at 1/2
    direct_flow: bool = False  # ResFlowNet predicts the whole flow from the frames (GeoNet's DirFlowNet ablation)
    gate_width: int = GATE_WIDTH  # with --pose-gate: the motion gate's first width (its convs: w, 2w, 2w, 4w, 4w)
    bn_momentum: float = 1e-3
    mask_out_of_view: bool = False  # deviation: rigid loss ignores pixels warped from outside the source
    automask: bool = False  # deviation: rigid loss ignores pixels the unwarped source already explains
    channels_last: bool = True  # NHWC convolutions: ~2x faster on CPU for the small nets
    scale_normalize: bool = False  # official option (its model_sn): each disparity map / its mean
    device: str = "auto"  # auto | cpu | cuda | cuda:N (under torchrun: cuda = this rank's GPU)
    amp: str = "off"  # mixed precision for the nets: off | bf16 | fp16 (fp16: CUDA, with a grad scaler)
    compile: bool = False  # torch.compile the stage's loss
    sync_bn: bool = False  # under torchrun: batch statistics over all ranks
    log_every: int = 10
    save_every: int = 500
    val_every: int = 500
    val_batches: int = 20
    weights: LossWeights = field(default_factory=LossWeights)

    @property
    def num_source(self) -> int:
        return self.seq_length - 1

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> TrainConfig:
        d = dict(d)
        d["weights"] = LossWeights(**d.get("weights", {}))
        known = {f.name for f in fields(cls)}
        unknown = set(d) - known
        if unknown:
            raise ValueError(f"unknown config keys {sorted(unknown)}")
        return cls(**d)


WEIGHT_FLAGS = (  # the LossWeights set from the command line, each `--NAME W`: (field, help)
    (
        "depth_supervision",
        "stage rigid: add W x the scale-invariant log-depth error against the ground truth of "
        "samples that have it (synthetic data prepared with --train-depth; real samples have none "
        "and keep only the self-supervised loss). Not in GeoNet: supervised synthetic pre-training",
    ),
    (
        "flow_supervision",
        "stage flow: add W x the end-point error of the full flow target -> next frame "
        "against the ground truth of samples that have it (synthetic data prepared with "
        "--train-flow; others keep only the self-supervised loss). Not in GeoNet",
    ),
    (
        "pose_supervision",
        "stage rigid: add W x the scale-aligned pose error (translation relative to the path "
        "length + chordal rotation) against the true motion of samples that have it (KITTI odometry "
        "or synthetic data prepared with --train-pose; others keep only the self-supervised loss). Not in GeoNet",
    ),
    (
        "pose_speed",
        "stage rigid, with --pose-supervision: add W x the speed error, each moving snippet's "
        "predicted path against its true one under one unit for the whole run (the scale-aligned "
        "error fits one per snippet, so it never teaches how fast the camera moves). Use it where "
        "every sample with true poses comes from one camera rig. Not in GeoNet",
    ),
    (
        "pose_keep",
        "stage rigid: add W x the difference between PoseNet's motions and those of the PoseNet it "
        "started from (--init-checkpoint) on the samples without true poses, so fine-tuning on still "
        "copies keeps how the starting net drives. Not with --resume. Not in GeoNet",
    ),
    (
        "pose_keep_shape",
        "stage rigid: as --pose-keep, but on the motion's shape only: each snippet's translations "
        "divided by its path length, so step directions and length ratios are held and its speed is "
        "free for the still copies to teach. Not with --resume. Not in GeoNet",
    ),
    (
        "pose_steady",
        "stage rigid: add W x the spread of each snippet's step lengths relative to its mean step "
        "(the speed barely changes within a snippet; no truth needed). Not in GeoNet",
    ),
    (
        "pose_stride",
        "stage rigid: add W x the log-ratio error of each stride2 copy's translations against twice "
        "those of its target's normal snippet, loaded beside it with the same augmentation (teaches "
        "how fast, not only whether, the camera moves; no truth needed; data prepared with "
        "--motion-mix ...stride2=P...). Not in GeoNet",
    ),
    (
        "pose_gate",
        "give PoseNet a motion gate (a small net whose probability that the camera moves multiplies every "
        "pose; W > 0 in every stage of such a model, so its checkpoints load) and, in stage rigid, add W x "
        "its cross-entropy against the snippets' motion (still: identity true poses, e.g. the still copies of "
        "--motion-mix and synthetic stops; moving: every other snippet, with or without true poses). "
        "Not in GeoNet",
    ),
    (
        "pose_overlap",
        "stage rigid: add W x the squared log-ratio of the step t -> t+1 as two overlapping snippets "
        "give it: each snippet's (t-1, t, t+1) and the next target's (t, t+1, t+2), loaded beside it "
        "with the same augmentation (the speed of neighbouring calls agrees; no truth needed). Not in "
        "GeoNet",
    ),
)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m training.train",
        description="Train GeoNet stage-wise. Stage 'rigid' trains DepthNet+PoseNet from scratch; "
        "stage 'flow' loads a rigid checkpoint, freezes it (eval-mode BN) and trains "
        "ResFlowNet. Data: a folder made by `python -m training.prepare`.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    d = TrainConfig()
    p.add_argument("--stage", choices=STAGES, default=d.stage)
    p.add_argument(
        "--arch",
        choices=ARCHS,
        default=d.arch,
        help="DepthNet encoder; 'small' also selects the small PoseNet and ResFlowNet",
    )
    p.add_argument("--data-dir", default=d.data_dir, help="prepared data (train.txt, val.txt)")
    p.add_argument(
        "--extra-data-dir",
        dest="extra_data_dirs",
        action="append",
        default=[],
        metavar="DIR",
        help="another prepared folder whose train.txt samples are mixed into the shuffled training "
        "batches (repeatable; e.g. your own footage next to the synthetic scenes); validation "
        "stays on --data-dir",
    )
    p.add_argument("--out-dir", default=d.out_dir, help="checkpoints and log.jsonl go here")
    p.add_argument(
        "--init-checkpoint",
        default=d.init_checkpoint,
        help="start from these weights (a checkpoint or a weights-only file), fresh optimizer: stage rigid "
        "fine-tunes its DepthNet/PoseNet; stage flow freezes them (and fine-tunes its ResFlowNet, if any)",
    )
    p.add_argument("--resume", default=d.resume, help="checkpoint of the same stage to continue exactly")
    p.add_argument("--seq-length", type=int, default=d.seq_length, help="3 for depth/flow, 5 for pose")
    p.add_argument("--height", type=int, default=d.height)
    p.add_argument("--width", type=int, default=d.width)
    p.add_argument(
        "--batch-size",
        type=int,
        default=d.batch_size,
        help="per process; under torchrun the effective batch is this x the number of ranks",
    )
    p.add_argument("--lr", type=float, default=d.lr)
    p.add_argument("--beta1", type=float, default=d.beta1, help="Adam")
    p.add_argument("--beta2", type=float, default=d.beta2, help="Adam")
    p.add_argument("--max-steps", type=int, default=d.max_steps)
    p.add_argument(
        "--max-minutes",
        type=float,
        default=d.max_minutes,
        help="stop (and save) once this much wall time has passed, even before --max-steps",
    )
    p.add_argument("--seed", type=int, default=d.seed)
    p.add_argument("--num-workers", type=int, default=d.num_workers, help="data-loading processes")
    p.add_argument("--no-augment", dest="augment", action="store_false")
    p.add_argument(
        "--share-color-gain",
        action="store_true",
        help="one colour gain for all frames of a sample (the official code draws one per frame)",
    )
    p.add_argument(
        "--freeze-depth",
        action="store_true",
        help="stage rigid: train PoseNet alone and keep DepthNet as --init-checkpoint has it (its batch-norm "
        "statistics too)",
    )
    p.add_argument(
        "--gate-only",
        action="store_true",
        help="stage rigid with --pose-gate: train the motion gate alone on its labels (DepthNet and the rest "
        "of PoseNet kept as --init-checkpoint has them and not run: no photometric loss)",
    )
    p.add_argument(
        "--rigid-corruption",
        type=float,
        default=d.rigid_corruption,
        metavar="C",
        help="stage flow: ResFlowNet trains on rigid flows made from poses scaled per snippet by a factor "
        "log-uniform in [1/C, C], and zero for a quarter of the snippets, so it learns to correct a wrong "
        "rigid flow (1 = off, as GeoNet). Validation and inference use the poses as they are",
    )
    p.add_argument(
        "--hard-gate",
        action="store_true",
        help="with --pose-gate: outside training (inference, export, the frozen PoseNet of stage flow) the gate "
        "is a step at probability 1/2, so a moving snippet's poses pass exactly as the trunk gives them and a "
        "still one's are zero",
    )
    p.add_argument(
        "--gate-width",
        type=int,
        default=d.gate_width,
        metavar="W",
        help="with --pose-gate: the motion gate's five convolutions are W, 2W, 2W, 4W and 4W channels wide "
        "(W=16: 70,689 parameters, W=8: 18,065); a run from a gated model keeps that model's width",
    )
    p.add_argument(
        "--direct-flow",
        action="store_true",
        help="ResFlowNet predicts the whole flow from the two frames, its rigid channels fed as for a camera at "
        "rest (the source frame, zero flow, the unwarped photometric error): GeoNet's DirFlowNet ablation "
        "(paper Table 4) in ResFlowNet's interface; the exported resflownet.onnx subtracts the rigid flow it is "
        "given, so the runtime's flow is this flow. Stage flow trains without running DepthNet and PoseNet",
    )
    p.add_argument(
        "--bn-momentum",
        type=float,
        default=d.bn_momentum,
        help="PyTorch BN momentum; 1e-3 = official TF decay 0.999 (slow for short runs)",
    )
    p.add_argument(
        "--mask-out-of-view",
        action="store_true",
        help="leave pixels whose rigid flow lands outside the source frame out of the rigid "
        "photometric loss (not in the official code; stops far-depth artefacts at the "
        "image border on forward-moving sequences)",
    )
    p.add_argument(
        "--automask",
        action="store_true",
        help="monodepth2's auto-mask: leave out pixels where the unwarped source matches the "
        "target better than the rigid warp (objects moving with the camera, sky); "
        "not in the official code",
    )
    p.add_argument(
        "--nchw",
        dest="channels_last",
        action="store_false",
        help="keep NCHW memory format (default: channels_last, faster on CPU)",
    )
    p.add_argument(
        "--scale-normalize",
        action="store_true",
        help="official option behind its released model_sn (not in the paper): divide each "
        "predicted disparity map by its spatial mean before warping and smoothness",
    )
    for name, text in WEIGHT_FLAGS:
        flag = "--" + name.replace("_", "-")
        p.add_argument(flag, type=float, default=getattr(d.weights, name), metavar="W", help=text)
    p.add_argument(
        "--device",
        default=d.device,
        help="auto (CUDA if present, else CPU), cpu, cuda or cuda:N; under torchrun each rank "
        "takes the GPU of its LOCAL_RANK",
    )
    p.add_argument(
        "--amp",
        choices=AMP_MODES,
        default=d.amp,
        help="mixed precision for the nets (geometry and losses stay float32); fp16 needs CUDA and uses a grad scaler",
    )
    p.add_argument("--compile", action="store_true", help="torch.compile the stage's loss (slow first steps)")
    p.add_argument(
        "--sync-bn",
        action="store_true",
        help="under torchrun: BatchNorm statistics over the whole effective batch (all ranks)",
    )
    p.add_argument("--log-every", type=int, default=d.log_every)
    p.add_argument("--save-every", type=int, default=d.save_every)
    p.add_argument("--val-every", type=int, default=d.val_every)
    p.add_argument("--val-batches", type=int, default=d.val_batches)
    return p


def config_from_args(argv=None) -> TrainConfig:
    args = vars(build_parser().parse_args(argv))
    weights = LossWeights(**{name: args.pop(name) for name, _ in WEIGHT_FLAGS})
    return TrainConfig(**args, weights=weights)
