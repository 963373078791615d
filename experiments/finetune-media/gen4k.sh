set -e
G=/work/main/.venv/bin/generate-dataset
$G --scenes 20 --families media --seed 7 --res 128 --spp 4,16,64,128 --ref-spp 4096 --out /work/ft/data/media-ft4k --quiet
$G --scenes 16 --families media --seed 8 --val-fraction 0.99 --res 128 --spp 4,16,64,128 --ref-spp 4096 --out /work/ft/data/media-test4k --quiet
echo done
