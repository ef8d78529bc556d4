#!/bin/bash
# usage: digestname_ab.sh TREE OUTROOT  -- encodes the scenes with TREE's splatstream; CPU time per encode to OUTROOT/times.txt
TREE=$1; OUT=$2
PY=/work/main/.venv/bin/python
R=/work/shared/data/real
mkdir -p $OUT
cd $TREE
for s in guitar:$R/guitar.compressed.ply donut:$R/donut_sh0_no_normals.ply massa:$R/statues/massa.sog; do
  n=${s%%:*}; f=${s#*:}
  for mode in short whole; do
    flag=""; [ $mode = whole ] && flag="--no-short-digests"
    /usr/bin/time -f "$n $mode %U user %S sys %e wall" -a -o $OUT/times.txt \
      env PYTHONPATH=. nice -n 19 $PY -m cli encode $f $OUT/${n}_$mode $flag -q || echo "FAIL $n $mode" >> $OUT/times.txt
  done
done
# fsspec (local:// through FsspecWriter) and a partitioned (Dask, 2 workers) encode of guitar
/usr/bin/time -f "guitar dask %U user %S sys %e wall" -a -o $OUT/times.txt env PYTHONPATH=. nice -n 19 $PY -m cli encode $R/guitar.compressed.ply $OUT/guitar_dask --workers 2 -q || echo "FAIL dask" >> $OUT/times.txt
echo done >> $OUT/times.txt
#!/bin/bash
# usage: digestname_ab2.sh TREE OUTROOT -- the other naming paths: codebook, paged, one tile, 1.8 table
TREE=$1; OUT=$2
PY=/work/main/.venv/bin/python
R=/work/shared/data/real
mkdir -p $OUT; cd $TREE
run() { n=$1; shift; env PYTHONPATH=. nice -n 19 $PY -m cli encode "$@" $OUT/$n -q || echo "FAIL $n" >> $OUT/fails.txt; }
run fruit_codebook $R/fruit_drops_sh3.ply --sh-codebook 64
run fruit_codebook_whole $R/fruit_drops_sh3.ply --sh-codebook 64 --no-short-digests
run guitar_paged $R/guitar.compressed.ply --page-tiles 40
run massa_onetile $R/statues/massa.sog --no-lod
run donut_table18 $R/donut_sh0_no_normals.ply --no-compact-table
echo done >> $OUT/fails.txt
# fruit_cbtree_{short,whole} (run by hand with each tree): encode $R/fruit_drops_sh3.ply OUT --sh-codebook 64 --max-leaf-splats 300 -q [--no-short-digests]
