#!/usr/bin/env bash
# Rebuild the bundled default model geonet_infer/models/small_synth, the demo sample and
# the model card docs/models.md from scratch with our own code, on a 2-core CPU:
#   1. synthetic driving scenes (40 sequences x 40 frames, seed 2026; 4 held out), prepared;
#   2. stage rigid: small DepthNet + PoseNet (--mask-out-of-view --automask, see docs/results.md);
#   3. stage flow: small ResFlowNet on the frozen rigid nets, FLOW_STEPS steps (the bundled model:
#      a 15-minute run to step 366, continued with --resume to step 2008);
#   3b. the same ResFlowNet, FLOWSUP_STEPS more steps with --flow-supervision 0.1 on the same
#      sequences prepared with --train-flow (the bundled model: a 60-minute run, 1870 steps, started
#      from the published weights of step 3, i.e. with conv kernels rounded to float16), then
#      FLOWSUP2_STEPS with --flow-supervision 1.0 (a 50-minute run to step 1074, continued with
#      --resume to step 4492, then to step 7342);
#   3c. FLOWSUP3_STEPS more (the bundled model: a 45-minute run to step 3001) at lr 2e-5 with 40 more
#      sequences (seed 2028, none held out) mixed in: more scenes, not more steps, closed the gap to
#      the held-out sequences (docs/training.md, runs J and K);
#   3d. stage rigid again, from 3c's published weights (DepthNet/PoseNet of step 2), RIGID2_STEPS more at
#      lr 2e-4 on both sets of sequences (the bundled model: an 85-minute run, 9582 steps; run L in
#      docs/training.md): more scenes and steps, and it revives the dead last decoder layer that gave
#      step 2's depth a floor;
#   3e. 3c's ResFlowNet put on those rigid nets and re-fitted with 3c's settings, FLOWSUP4_STEPS steps (the
#      bundled model: a 35-minute run to step 2578, continued with --resume to step 5138, then to 8271;
#      runs M, N and N2);
#   3f. (since issue 32, not run by this script) DepthNet/PoseNet fine-tuned 1290 steps on real footage
#      with the pose loss: round 2 of `scripts/real_pose_finetune.sh` from 3e's weights, INT8 with
#      --int8-ops Conv,Relu,Add,MaxPool (docs/training.md, "Real footage and true poses");
#   3g. (since issue 53, not run by this script) a motion gate added to PoseNet and ResFlowNet retrained as a
#      direct flow net, its batch-norm statistics recomputed: round 21 of `scripts/stop_finetune.sh`
#      (docs/training.md, "Rounds 19–21");
#   4. ONNX export fp32 + INT8 (calibrated on training sequence seq_0000, never a held-out one),
#      with the INT8 accuracy delta on the held-out sequences written into the manifest;
#   5. copy into the package, publish the checkpoint's weights (weights/small_synth.pt, to fine-tune
#      from), take 12 frames of held-out seq_0038 as the demo sample, write the model card
#      (synthetic held-out + real KITTI frames 0-9 against Velodyne; with BEFORE=<commit>, the
#      bundled model of that commit measured beside it) and the README's demo picture.
# Environment: RIGID_MINUTES (45) caps stage rigid (wall clock), FLOW_STEPS (2008) sets stage flow,
# FLOWSUP_STEPS (1870), FLOWSUP2_STEPS (7342) and FLOWSUP3_STEPS (3001) its flow-supervised continuations,
# RIGID2_STEPS (9582) the second rigid run and FLOWSUP4_STEPS (8271) the flow re-fit on it;
# THREADS (1) torch threads: one thread per training process keeps OpenMP from stalling
# when anything else runs on the machine.
set -euo pipefail
cd "$(dirname "$0")/.."
RIGID_MINUTES=${RIGID_MINUTES:-45}
FLOW_STEPS=${FLOW_STEPS:-2008}
FLOWSUP_STEPS=${FLOWSUP_STEPS:-1870}
FLOWSUP2_STEPS=${FLOWSUP2_STEPS:-7342}
FLOWSUP3_STEPS=${FLOWSUP3_STEPS:-3001}
RIGID2_STEPS=${RIGID2_STEPS:-9582}
FLOWSUP4_STEPS=${FLOWSUP4_STEPS:-8271}
export OMP_NUM_THREADS=${THREADS:-1}
PY=.venv/bin/python
[ -x "$PY" ] || { python3 -m venv .venv && $PY -m pip install --quiet -e '.[train,dev]'; }
run() { echo "+ $*"; "$@"; }
DATA=data/synth40 PREP=data/synth40_prepared RIGID=runs/small_rigid FLOW=runs/small_flow
PREP_FLOW=data/synth40_flow FLOWSUP=runs/small_flowsup FLOWSUP2=runs/small_flowsup2
MORE=data/synthB MORE_FLOW=data/synthB_flow FLOWSUP3=runs/small_flowsup3
RIGID2=runs/small_rigid2 FLOWSUP4=runs/small_flowsup4
[ -f "$DATA/seq_0039/poses.txt" ] || run $PY -m training.synth --out $DATA --sequences 40 --frames 40 --seed 2026 --workers 2
[ -f "$PREP/heldout.txt" ] || run $PY -m training.prepare --kind synth --src $DATA --out $PREP --heldout 4 --workers 2
run $PY -m training.train --stage rigid --arch small --data-dir $PREP --out-dir $RIGID \
    --max-steps 6000 --max-minutes "$RIGID_MINUTES" --bn-momentum 0.01 --mask-out-of-view --automask \
    --num-workers 1 --val-every 500 --save-every 250 --log-every 25
run $PY -m training.train --stage flow --arch small --data-dir $PREP --out-dir $FLOW \
    --init-checkpoint $RIGID/last.pt --max-steps "$FLOW_STEPS" --bn-momentum 0.01 \
    --num-workers 1 --val-every 250 --save-every 250 --log-every 25
[ -f "$PREP_FLOW/heldout.txt" ] || run $PY -m training.prepare --kind synth --src $DATA --out $PREP_FLOW \
    --heldout 4 --workers 2 --train-flow
run $PY -m training.train --stage flow --arch small --data-dir $PREP_FLOW --out-dir $FLOWSUP \
    --init-checkpoint $FLOW/last.pt --flow-supervision 0.1 --max-steps "$FLOWSUP_STEPS" --bn-momentum 0.01 \
    --num-workers 1 --val-every 250 --save-every 250 --log-every 25
run $PY -m training.train --stage flow --arch small --data-dir $PREP_FLOW --out-dir $FLOWSUP2 \
    --init-checkpoint $FLOWSUP/last.pt --flow-supervision 1.0 --max-steps "$FLOWSUP2_STEPS" --bn-momentum 0.01 \
    --num-workers 1 --val-every 250 --save-every 250 --log-every 25
[ -f "$MORE/seq_0039/poses.txt" ] || run $PY -m training.synth --out $MORE --sequences 40 --frames 40 --seed 2028 --workers 2
[ -f "$MORE_FLOW/train.txt" ] || run $PY -m training.prepare --kind synth --src $MORE --out $MORE_FLOW \
    --heldout 0 --workers 2 --train-flow
run $PY -m training.train --stage flow --arch small --data-dir $PREP_FLOW --extra-data-dir $MORE_FLOW \
    --out-dir $FLOWSUP3 --init-checkpoint $FLOWSUP2/last.pt --flow-supervision 1.0 --lr 2e-5 \
    --max-steps "$FLOWSUP3_STEPS" --bn-momentum 0.01 --num-workers 1 --val-every 250 --save-every 250 --log-every 25
run $PY -m training.checkpoint --weights-only $FLOWSUP3/last.pt $FLOWSUP3/weights.pt
run $PY -m training.train --stage rigid --arch small --data-dir $PREP --extra-data-dir $MORE_FLOW \
    --out-dir $RIGID2 --init-checkpoint $FLOWSUP3/weights.pt --lr 2e-4 --max-steps "$RIGID2_STEPS" \
    --bn-momentum 0.01 --mask-out-of-view --automask --num-workers 1 --val-every 500 --save-every 250 --log-every 25
run $PY -m training.checkpoint --combine $RIGID2/last.pt $FLOWSUP3/weights.pt $RIGID2/with_flow.pt
run $PY -m training.train --stage flow --arch small --data-dir $PREP_FLOW --extra-data-dir $MORE_FLOW \
    --out-dir $FLOWSUP4 --init-checkpoint $RIGID2/with_flow.pt --flow-supervision 1.0 --lr 2e-5 \
    --max-steps "$FLOWSUP4_STEPS" --bn-momentum 0.01 --num-workers 1 --val-every 500 --save-every 250 --log-every 25
run $PY -m export --checkpoint $FLOWSUP4/last.pt --out models/small_synth --force \
    --precision fp32,int8 --calib-data $DATA/seq_0000/image --calib-method percentile --calib-frames 40 \
    --eval-synth-dir $DATA --eval-prepared-dir $PREP --eval-stride 2
rm -rf geonet_infer/models/small_synth
cp -r models/small_synth geonet_infer/models/small_synth
run $PY -m training.checkpoint --weights-only $FLOWSUP4/last.pt weights/small_synth.pt
rm -rf geonet_infer/samples/synth_seq && mkdir -p geonet_infer/samples/synth_seq/image
cp $DATA/seq_0038/calib.txt geonet_infer/samples/synth_seq/calib.txt
for i in $(seq -w 0 11); do cp $DATA/seq_0038/image/0000$i.png geonet_infer/samples/synth_seq/image/; done
before=()
if [ -n "${BEFORE:-}" ]; then
    rm -rf runs/before && mkdir -p runs/before
    git archive "$BEFORE" geonet_infer/models/small_synth | tar -x -C runs/before
    before=(--before runs/before/geonet_infer/models/small_synth)
fi
run $PY -m benchmarks.model_card --model geonet_infer/models/small_synth --synth-dir $DATA --prepared-dir $PREP \
    --kitti ../shared/realdata/kitti_raw_2011_09_26_sfnd --out docs/models.md --json docs/models.json "${before[@]}"
.venv/bin/python -m pip install --quiet -e .
run .venv/bin/geonet-infer demo --out runs/demo --no-progress
mkdir -p docs/img && cp runs/demo/demo.png docs/img/demo.png
echo "done: geonet_infer/models/small_synth, docs/models.md, docs/img/demo.png"
