# The held-out family's data: 20 media scenes to fine-tune on (seed 7) and 16 to score (seed 8),
# once with 1024-spp references (media-ft, media-test) and once with 4096 (media-ft4k, media-test4k).
set -e
G=/work/main/.venv/bin/generate-dataset
for ref in 1024 4096; do
  suffix=$([ "$ref" = 4096 ] && echo 4k || true)
  $G --scenes 20 --families media --seed 7 --res 128 --spp 4,16,64,128 --ref-spp $ref --out /work/ft/data/media-ft$suffix --quiet
  $G --scenes 16 --families media --seed 8 --val-fraction 0.99 --res 128 --spp 4,16,64,128 --ref-spp $ref \
      --out /work/ft/data/media-test$suffix --quiet
done
echo done
