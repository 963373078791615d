# The same fine-tune without (reference, reference) pairs: the media references (1024 spp) are not converged.
set -e
cd /work/runs/code
export PYTHONPATH=/work/runs/code
for m in 10 30; do
  nice -n 5 /work/main/.venv/bin/python -c 'import sys; from training.cli import main; sys.argv[0]="train"; sys.exit(main())' \
      --recipe /work/ft/flat-s-allspp-nocp-lowlr.toml --data /work/ft/data/media-ft4k --init-from flat-s-allspp --cpu-minutes $m \
      --threads 1 --out /work/ft/runs/ft-media4k-lowlr --no-progress
  cp /work/ft/runs/ft-media4k-lowlr/finetune/best.ckpt /work/ft/runs/ft-media4k-lowlr-$m.ckpt
  cp /work/ft/runs/ft-media4k-lowlr/finetune/last.ckpt /work/ft/runs/ft-media4k-lowlr-$m-last.ckpt
done
echo nocp done
