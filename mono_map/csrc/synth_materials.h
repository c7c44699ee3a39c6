/* Material ids and the LiDAR reflectance table of mono_map/data/synth/materials.py, for synth.c
   (tests/test_synth.py checks they agree with materials.py). */
#ifndef MONO_MAP_SYNTH_MATERIALS_H
#define MONO_MAP_SYNTH_MATERIALS_H
#define MAT_SKY 0
#define MAT_GROUND 1
#define MAT_CURB 2
#define MAT_FACADE 3
#define MAT_CAR_PAINT 4
#define MAT_CAR_GLASS 5
#define MAT_TYRE 6
#define MAT_TRUNK 7
#define MAT_FOLIAGE 8
#define MAT_METAL 9
#define MAT_FENCE 10
#define MAT_LAMP 11
static inline double lidar_refl(int m) { switch (m) { case 2: return 0.35; case 5: return 0.05; case 6: return 0.1; case 7: return 0.3; case 8: return 0.4; case 9: return 0.45; case 10: return 0.3; case 11: return 0.6; default: return 0.3; } }
#endif
