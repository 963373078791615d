# Held-out family fine-tune: flat-s-allspp (its whole lineage predates the media family) fitted to
# 20 media scenes for 10, 30 and 60 CPU-minutes, one run resumed to each budget.
set -e
cd /work/runs/code
export PYTHONPATH=/work/runs/code
for m in 10 30 60; do
  nice -n 5 /work/main/.venv/bin/python -c 'import sys; from training.cli import main; sys.argv[0]="train"; sys.exit(main())' \
      --recipe flat-s-allspp --data /work/ft/data/media-ft --init-from flat-s-allspp --cpu-minutes $m \
      --threads 1 --out /work/ft/runs/ft-media
  cp /work/ft/runs/ft-media/finetune/best.ckpt /work/ft/runs/ft-media-$m.ckpt
  cp /work/ft/runs/ft-media/finetune/last.ckpt /work/ft/runs/ft-media-$m-last.ckpt
done
echo ft done
