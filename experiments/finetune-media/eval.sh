# Held-out family (media) fine-tunes of flat-s-allspp scored on 16 unseen media scenes (4096-spp references).
set -e
cd /work/main
R=/work/ft/runs
.venv/bin/python -m benchmarks.validation --data /work/ft/data/media-test4k --models flat-s-allspp,recipe-10=$R/ft-media-10.ckpt,recipe-30=$R/ft-media-30.ckpt,recipe-60=$R/ft-media-60.ckpt,recipe-60-last=$R/ft-media-60-last.ckpt,nopairs-10=$R/ft-media-nocp-10.ckpt,nopairs-30=$R/ft-media-nocp-30.ckpt,ref4096-10=$R/ft-media4k-10.ckpt,ref4096-nopairs-lr5e-5-10=$R/ft-media4k-lowlr-10.ckpt --out /work/ft/res/all
.venv/bin/python -m benchmarks.evaluate --models flat-s-allspp,$R/ft-media-nocp-30.ckpt,$R/ft-media-60.ckpt --spp 4,16,128 --out /work/ft/res/forget --quiet
echo eval done
