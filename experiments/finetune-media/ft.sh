# One held-out-family fine-tune of flat-s-allspp (its whole lineage predates the media family),
# one run resumed to each CPU budget in turn:
#   ft.sh RECIPE DATA NAME MINUTES...  -> /work/ft/runs/NAME-M.ckpt (best) and NAME-M-last.ckpt
# The runs measured (docs/training.md, "What a fine-tune buys, measured"):
#   ft.sh flat-s-allspp-as-run.toml     media-ft   ft-media         10 30 60  # the recipe then: with (reference, reference) pairs
#   ft.sh flat-s-allspp-as-run.toml     media-ft4k ft-media4k       10 30     # the same on 4096-spp references
#   ft.sh flat-s-allspp-nocp.toml       media-ft   ft-media-nocp    10 30     # without the pairs (the recipe now)
#   ft.sh flat-s-allspp-nocp-lowlr.toml media-ft4k ft-media4k-lowlr 10 30     # without the pairs, lr 5e-5
set -e
recipe=$(cd "$(dirname "$0")" && pwd)/$1
data=/work/ft/data/$2
name=$3
shift 3
cd /work/runs/code
export PYTHONPATH=/work/runs/code
for m in "$@"; do
  nice -n 5 /work/main/.venv/bin/python -c 'import sys; from training.cli import main; sys.argv[0]="train"; sys.exit(main())' \
      --recipe "$recipe" --data "$data" --init-from flat-s-allspp --cpu-minutes "$m" \
      --threads 1 --out "/work/ft/runs/$name" --no-progress
  cp "/work/ft/runs/$name/finetune/best.ckpt" "/work/ft/runs/$name-$m.ckpt"
  cp "/work/ft/runs/$name/finetune/last.ckpt" "/work/ft/runs/$name-$m-last.ckpt"
done
echo "$name done"
