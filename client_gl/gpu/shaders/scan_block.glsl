// Exclusive scan of SCAN_TILE values held as SCAN_ITEMS consecutive values per thread (256 threads).
shared uint s_scan[256];

// vals: this thread's SCAN_ITEMS values, in order; returns them replaced by their exclusive prefix within the block
// and the block total through `total`.
void block_exclusive_scan(inout uint vals[SCAN_ITEMS], out uint total) {
    uint lid = gl_LocalInvocationID.x;
    uint run = 0u;
    for (uint i = 0u; i < SCAN_ITEMS; ++i) {
        uint v = vals[i];
        vals[i] = run;
        run += v;
    }
    s_scan[lid] = run;
    barrier();
    // Hillis-Steele inclusive scan of the per-thread sums.
    for (uint off = 1u; off < 256u; off <<= 1) {
        uint add = lid >= off ? s_scan[lid - off] : 0u;
        barrier();
        s_scan[lid] += add;
        barrier();
    }
    uint before = s_scan[lid] - run;
    total = s_scan[255];
    for (uint i = 0u; i < SCAN_ITEMS; ++i) vals[i] += before;
    barrier();
}
