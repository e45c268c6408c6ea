#!/bin/sh
# The sim-to-real table of the lane-change predictors (docs/components/real-data.md, "The
# sim-to-real table"), from nothing but the two US-101 development files: imports, the frozen
# splits (splits/), simulated datasets, the trained models, the re-tuned decisions and the table.
# Seeded throughout (training: --seed 0 --threads 1); about 175 min on 2 CPU cores, most of it
# simulation and training. Steps already done (their output exists) are skipped.
#   tools/sim_to_real.sh NGSIM_FILE COMMONROAD_ARCHIVE [WORK_DIR]   (default runs/sim-to-real)
# NGSIM_FILE: ngsim_us101_0750-0805_first65535rows.csv.gz; COMMONROAD_ARCHIVE:
# commonroad_ngsim_us101.tar.xz (their README says where they come from). The table lands in
# WORK_DIR/table/sim_to_real.{md,csv,json}, the longer-trained GRUs' in WORK_DIR/table-long/, the sway
# inputs' comparison in WORK_DIR/matched_sway.md, the seed ensembles' in WORK_DIR/matched_ensembles.md
# and WORK_DIR/agreement_*.md.
set -eu
NGSIM="$1"; CR="$2"; W="${3:-runs/sim-to-real}"
V="${PYTHON:-python} -m vcfusion"
D="$W/data"; M="$W/models"
mkdir -p "$D" "$M"
step() { [ -e "$1" ] && return 0; shift; echo "+ $*"; "$@"; }

# real recordings and their frozen splits (train = development, validation, test = held-out)
step "$D/ngsim" $V dataset --from-ngsim "$NGSIM" --out "$D/ngsim"
step "$D/cr" $V dataset --from-commonroad "$CR" --out "$D/cr"
step "$D/ngsim-split" $V real-split apply "$D/ngsim" splits/us101_ngsim_0750.json --out "$D/ngsim-split"
step "$D/cr-split" $V real-split apply "$D/cr" splits/us101_commonroad.json --out "$D/cr-split"
REAL="$D/ngsim-split $D/cr-split"

# simulated families: calibrated (SL2015 tuned to US-101) and SUMO's LC2013; heavy is held out
CAL=""; LC=""
for f in dense free onramp accident_left accident_middle v2c_poor; do
  step "$D/${f}_us101/dataset.json" $V dataset "scenarios/calibrated/${f}_us101.yaml" --seeds 0-19 \
      --out "$D/${f}_us101" --workers 2
  step "$D/lc_$f/dataset.json" $V dataset "scenarios/families/$f.yaml" --seeds 0-19 --out "$D/lc_$f" --workers 2
  CAL="$CAL $D/${f}_us101"; LC="$LC $D/lc_$f"
done
step "$D/heavy_us101/dataset.json" $V dataset scenarios/calibrated/heavy_us101.yaml --seeds 0,2-6 \
    --out "$D/heavy_us101" --workers 2
step "$D/heavy/dataset.json" $V dataset scenarios/families/heavy.yaml --seeds 0,2-6 --out "$D/heavy" --workers 2

# models: on calibrated simulation (two input sets), on real development data, on simulation
# then fine-tuned on real development data; decisions tuned on the validation seeds they name
T="--kind gru --seed 0 --threads 1"
# shellcheck disable=SC2086
{
step "$M/sim_base.npz" $V train $CAL $T --inputs base --epochs 3 --out "$M/sim_base.npz"
step "$M/sim_lat.npz" $V train $CAL $T --inputs lateral --epochs 3 --out "$M/sim_lat.npz"
step "$M/mix_lat.npz" $V train $LC $CAL $T --inputs lateral --epochs 3 --out "$M/mix_lat.npz"
step "$M/real_lat.npz" $V train $REAL $T --inputs lateral --epochs 10 --patience 4 --false-alarm-budget 5 \
    --out "$M/real_lat.npz"
for base in sim_lat mix_lat; do
  step "$M/ft_$base.npz" $V train $REAL $T --init "$M/$base.npz" --epochs 10 --patience 4 --learning-rate 3e-4 \
      --false-alarm-budget 5 --out "$M/ft_$base.npz"
  SIM="$CAL"; [ "$base" = mix_lat ] && SIM="$LC $CAL"  # the simulation the model was pretrained on
  step "$M/ft_${base}_simtuned.npz" $V retune "$M/ft_$base.npz" $SIM --false-alarm-budget 1.5 \
      --out "$M/ft_${base}_simtuned.npz"
done
# the mixed-sim fine-tuned GRU with a decision chosen on cross-fitted validation streams of the
# development and validation parts (docs/components/real-data.md, "False alarms on real data")
step "$M/ft_mix_lat_cv.npz" ${PYTHON:-python} tools/real_alarms_cv.py "$D/ngsim" "$D/cr" "$M/mix_lat.npz" "$W/cv-mix" \
    --apply "$M/ft_mix_lat.npz" --out "$M/ft_mix_lat_cv.npz"
# the lateral motion over the vehicle's own sway as GRU inputs (docs/components/real-data.md, "Lateral
# speed over the vehicle's own sway"): the mixed-sim recipe with the "sway" inputs, and the mixed-sim
# GRU lateral with them appended at zero weight (learnt from the recordings only), each fine-tuned in
# the four folds; their curves against the candidate's at matched recall and false alarms
step "$M/mix_sway.npz" $V train $LC $CAL $T --inputs sway --epochs 3 --out "$M/mix_sway.npz"
step "$M/mix_lat_plus_sway.npz" ${PYTHON:-python} tools/extend_gru_inputs.py "$M/mix_lat.npz" "$D/ngsim-split" \
    "$D/cr-split" --inputs sway --out "$M/mix_lat_plus_sway.npz"
for m in mix_sway mix_lat_plus_sway; do
  step "$W/cv-$m/curve.csv" ${PYTHON:-python} tools/real_alarms_cv.py "$D/ngsim" "$D/cr" "$M/$m.npz" "$W/cv-$m"
done
${PYTHON:-python} tools/matched_curves.py "mixed-sim GRU lateral (candidate)=$W/cv-mix/curve.csv" \
    "mixed-sim GRU sway=$W/cv-mix_sway/curve.csv" "mixed-sim GRU lateral + sway (real only)=$W/cv-mix_lat_plus_sway/curve.csv" \
    --rates all:1.7,all:4,judged:3.4 --out "$W/matched_sway.md"
# ensembles of fine-tuning seeds (docs/components/real-data.md, "Ensembles of fine-tuning seeds"): the
# candidate's fold models fine-tuned again with seeds 1-9 (seed 0: cv-mix), each seed's curve, and the
# ensembles of the same fold models {0-4}, {5-9}, {0,1,2}, {3,4,5}, {6,7,8}; about 25 min (the sway
# models' ensembles below: about 20 min more)
ln -sfn cv-mix "$W/cv-seed0"
for s in 1 2 3 4 5 6 7 8 9; do
  mkdir -p "$W/cv-seed$s"
  for k in 0 1 2 3; do for n in ngsim cr; do ln -sfn "../cv-mix/$n-cv$k" "$W/cv-seed$s/$n-cv$k"; done; done
  step "$W/cv-seed$s/curve.csv" ${PYTHON:-python} tools/real_alarms_cv.py "$D/ngsim" "$D/cr" "$M/mix_lat.npz" \
      "$W/cv-seed$s" --seed "$s"
done
for e in 0,1,2,3,4 5,6,7,8,9 0,1,2 3,4,5 6,7,8; do
  E="$W/ens-$(echo "$e" | tr , -)"
  mkdir -p "$E"
  for k in 0 1 2 3; do
    for n in ngsim cr; do ln -sfn "../cv-mix/$n-cv$k" "$E/$n-cv$k"; done
    for s in $(echo "$e" | tr , ' '); do ln -sfn "../cv-seed$s/ft_cv$k.npz" "$E/ft_cv${k}_seed$s.npz"; done
  done
  step "$E/curve.csv" ${PYTHON:-python} tools/real_alarms_cv.py "$D/ngsim" "$D/cr" "$M/mix_lat.npz" "$E" --seeds "$e"
done
SEEDS=""
for s in 0 1 2 3 4 5 6 7 8 9; do SEEDS="$SEEDS seed$s=$W/cv-seed$s/curve.csv"; done
# shellcheck disable=SC2086
${PYTHON:-python} tools/matched_curves.py $SEEDS "{0,1,2}=$W/ens-0-1-2/curve.csv" "{3,4,5}=$W/ens-3-4-5/curve.csv" \
    "{6,7,8}=$W/ens-6-7-8/curve.csv" "{0-4}=$W/ens-0-1-2-3-4/curve.csv" "{5-9}=$W/ens-5-6-7-8-9/curve.csv" \
    --shares 63/94,70/94 --rates all:4 --out "$W/matched_ensembles.md"
# shellcheck disable=SC2086
${PYTHON:-python} tools/matched_curves.py $SEEDS --agreement --out "$W/agreement_seeds.md"
${PYTHON:-python} tools/matched_curves.py "{0,1,2}=$W/ens-0-1-2/curve.csv" "{3,4,5}=$W/ens-3-4-5/curve.csv" \
    "{6,7,8}=$W/ens-6-7-8/curve.csv" --agreement --out "$W/agreement_ens3.md"
${PYTHON:-python} tools/matched_curves.py "{0-4}=$W/ens-0-1-2-3-4/curve.csv" "{5-9}=$W/ens-5-6-7-8-9/curve.csv" \
    --agreement --out "$W/agreement_ens5.md"
# the sway GRU and the real-only lateral + sway GRU, each as an ensemble of five fine-tuning seeds
for m in mix_sway mix_lat_plus_sway; do
  step "$W/ens-$m/curve.csv" ${PYTHON:-python} tools/real_alarms_cv.py "$D/ngsim" "$D/cr" "$M/$m.npz" "$W/ens-$m" \
      --seeds 0,1,2,3,4
done
${PYTHON:-python} tools/matched_curves.py "candidate {0-4}=$W/ens-0-1-2-3-4/curve.csv" \
    "sway {0-4}=$W/ens-mix_sway/curve.csv" "real only {0-4}=$W/ens-mix_lat_plus_sway/curve.csv" \
    --rates all:1.7,all:4,judged:3.4 --out "$W/matched_ensembles_sway.md"
# the lateral GRUs trained longer (docs/components/real-data.md, "Longer training"): the 3-epoch
# files continued (--init: same inputs and standardisation) for at most 6 / 5 more epochs, stopped
# on the same validation seeds (patience 2), decision tuned there (<= 1.5 false alarms / veh-h)
step "$M/sim_lat_long.npz" $V train $CAL $T --init "$M/sim_lat.npz" --epochs 6 --patience 2 --out "$M/sim_lat_long.npz"
step "$M/mix_lat_long.npz" $V train $LC $CAL $T --init "$M/mix_lat.npz" --epochs 5 --patience 2 --out "$M/mix_lat_long.npz"
A=src/vcfusion/assets
for m in "$A/lane_change_gru.npz:shipped_gru" "$A/lane_change_mlp.npz:shipped_mlp" "$M/sim_base.npz:sim_base" \
         "$M/sim_lat.npz:sim_lat" "$M/mix_lat.npz:mix_lat" "$M/sim_lat_long.npz:sim_lat_long" \
         "$M/mix_lat_long.npz:mix_lat_long"; do
  step "$M/${m#*:}_realtuned.npz" $V retune "${m%%:*}" $REAL --false-alarm-budget 5 --out "$M/${m#*:}_realtuned.npz"
done
}

$V sim-to-real --bootstrap 1000 --seed 0 --out "$W/table" \
  --model "shipped MLP=$A/lane_change_mlp.npz" --model "shipped MLP, real-tuned=$M/shipped_mlp_realtuned.npz" \
  --model "shipped GRU=$A/lane_change_gru.npz" --model "shipped GRU, real-tuned=$M/shipped_gru_realtuned.npz" \
  --model "calibrated-sim GRU=$M/sim_base.npz" --model "calibrated-sim GRU, real-tuned=$M/sim_base_realtuned.npz" \
  --model "calibrated-sim GRU lateral=$M/sim_lat.npz" \
  --model "calibrated-sim GRU lateral, real-tuned=$M/sim_lat_realtuned.npz" \
  --model "mixed-sim GRU lateral=$M/mix_lat.npz" --model "mixed-sim GRU lateral, real-tuned=$M/mix_lat_realtuned.npz" \
  --model "real-trained GRU lateral=$M/real_lat.npz" \
  --model "fine-tuned GRU lateral (calibrated-sim)=$M/ft_sim_lat.npz" \
  --model "fine-tuned GRU lateral (calibrated-sim), sim-tuned=$M/ft_sim_lat_simtuned.npz" \
  --model "fine-tuned GRU lateral (mixed-sim)=$M/ft_mix_lat.npz" \
  --model "fine-tuned GRU lateral (mixed-sim), sim-tuned=$M/ft_mix_lat_simtuned.npz" \
  --model "fine-tuned GRU lateral (mixed-sim), cross-fit decision=$M/ft_mix_lat_cv.npz" \
  --eval "heavy LC2013 (held-out family)=$D/heavy:all" \
  --eval "heavy_us101 calibrated (held-out family)=$D/heavy_us101:all" \
  --eval "NGSIM US-101 held-out=$D/ngsim-split:test" --eval "CommonRoad US-101 held-out=$D/cr-split:test"

# the longer-trained GRUs next to the 3-epoch ones and the shipped GRU (real-data.md, "Longer training")
$V sim-to-real --bootstrap 1000 --seed 0 --out "$W/table-long" \
  --model "shipped GRU=$A/lane_change_gru.npz" \
  --model "calibrated-sim GRU lateral=$M/sim_lat.npz" --model "calibrated-sim GRU lateral, trained longer=$M/sim_lat_long.npz" \
  --model "calibrated-sim GRU lateral, trained longer, real-tuned=$M/sim_lat_long_realtuned.npz" \
  --model "mixed-sim GRU lateral=$M/mix_lat.npz" --model "mixed-sim GRU lateral, trained longer=$M/mix_lat_long.npz" \
  --model "mixed-sim GRU lateral, trained longer, real-tuned=$M/mix_lat_long_realtuned.npz" \
  --eval "heavy LC2013 (held-out family)=$D/heavy:all" \
  --eval "heavy_us101 calibrated (held-out family)=$D/heavy_us101:all" \
  --eval "NGSIM US-101 held-out=$D/ngsim-split:test" --eval "CommonRoad US-101 held-out=$D/cr-split:test"
