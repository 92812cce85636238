/*
 * agv_fe/estimate.h - read the AGV fault estimator's binary per-vehicle estimate (wire protocol version 1), in C99.
 *
 * A vehicle that closes its loop on its own estimates subscribes to agv_fe_vehicle_key(..., "estimate.bin") and
 * decodes each payload with agv_fe_decode_estimate(): a 40-byte header and N little-endian doubles, the record's
 * float columns in the order of AGV_FE_COLUMN_* (docs/protocol.md, "Estimate (binary, per vehicle)";
 * agv_protocol/wire.py, encode_binary_estimates). A column the record does not carry is NaN. Header only, no allocation; the decoder
 * reads every field byte by byte, so it is right on any host's endianness.
 */
#ifndef AGV_FE_ESTIMATE_H
#define AGV_FE_ESTIMATE_H

#include "agv_fe/measurement.h"

#define AGV_FE_ESTIMATE_HEADER_SIZE 40u
/* the revision of version 1's estimate record this side reads (1: revision 1.1, the effectiveness columns) */
#define AGV_FE_ESTIMATE_REVISION 1
/* the float columns, in wire order; a later revision appends, never reorders */
enum {
    AGV_FE_COLUMN_VX = 0,           /* estimated v_x [m/s] */
    AGV_FE_COLUMN_VY = 1,           /* estimated v_y [m/s] */
    AGV_FE_COLUMN_R = 2,            /* estimated yaw rate r [rad/s] */
    AGV_FE_COLUMN_TORQUE_FAULT = 3, /* estimated torque fault T_f [N m] */
    AGV_FE_COLUMN_STEER_FAULT = 4,  /* estimated steering fault delta_f [rad] */
    AGV_FE_COLUMN_TORQUE_BIAS = 5,  /* revision 1.1, effectiveness stage only: bias b_T [N m] */
    AGV_FE_COLUMN_STEER_BIAS = 6,   /* ... bias b_delta [rad] */
    AGV_FE_COLUMN_TORQUE_ALPHA = 7, /* ... effectiveness alpha_T [-] */
    AGV_FE_COLUMN_STEER_ALPHA = 8,  /* ... effectiveness alpha_delta [-] */
    AGV_FE_N_COLUMNS = 9
};
/* flag bits: premise in the design box; the gains have two sets; (with the previous bit) the fast set made it */
#define AGV_FE_ESTIMATE_IN_DOMAIN 0x01u
#define AGV_FE_ESTIMATE_GAIN_SET 0x02u
#define AGV_FE_ESTIMATE_FAST 0x04u
#define AGV_FE_ESTIMATE_KNOWN_FLAGS 0x07u
/* levels */
enum { AGV_FE_LEVEL_OK = 0, AGV_FE_LEVEL_WARN = 1, AGV_FE_LEVEL_FAULT = 2, AGV_FE_LEVEL_STALE = 3 };
#define AGV_FE_ERR_LEVEL (-7) /* a level code this side does not know */

/* The 40-byte header as it lies on the wire (little-endian); n_columns doubles follow it. */
#if defined(_MSC_VER)
#pragma pack(push, 1)
#endif
struct AGV_FE_PACKED agv_fe_estimate_header {
    char magic[4];         /*  0: "AGVE" */
    uint8_t version;       /*  4: 1 */
    uint8_t revision;      /*  5: revision of version 1 whose columns it carries (0: 1.0) */
    uint8_t flags;         /*  6: AGV_FE_ESTIMATE_* bits, others 0 */
    uint8_t level;         /*  7: AGV_FE_LEVEL_* */
    uint64_t seq;          /*  8: seq of the measurement it answers */
    int64_t timestamp_ns;  /* 16: that measurement's timestamp [ns] */
    char gain_version[12]; /* 24: ASCII, NUL-padded */
    uint16_t n_columns;    /* 36: doubles that follow */
    uint16_t reserved;     /* 38: zero */
};
#if defined(_MSC_VER)
#pragma pack(pop)
#endif
typedef char agv_fe_estimate_header_is_40_bytes[
    sizeof(struct agv_fe_estimate_header) == AGV_FE_ESTIMATE_HEADER_SIZE ? 1 : -1];

/* One estimate as the decoder gives it: every column this side knows (NaN where the record has none). */
typedef struct {
    uint8_t revision, flags, level;
    uint64_t seq;
    int64_t timestamp_ns;
    char gain_version[13]; /* NUL-terminated */
    double values[AGV_FE_N_COLUMNS];
} agv_fe_estimate;

/* Decode a payload with the service's checks; 0 or an AGV_FE_ERR_* code. A record of a later revision is read
 * for the columns this side knows; at a revision this side knows, more columns than it has is an error. */
static inline int agv_fe_decode_estimate(const uint8_t *p, size_t n, agv_fe_estimate *e) {
    if (n < AGV_FE_ESTIMATE_HEADER_SIZE) return AGV_FE_ERR_SIZE;
    if (memcmp(p, "AGVE", 4) != 0) return AGV_FE_ERR_MAGIC;
    if (p[4] != AGV_FE_PROTOCOL_VERSION) return AGV_FE_ERR_VERSION;
    if ((p[6] & ~AGV_FE_ESTIMATE_KNOWN_FLAGS) != 0 || agv_fe_get_le(p + 38, 2) != 0) return AGV_FE_ERR_RESERVED;
    if (p[7] > AGV_FE_LEVEL_STALE) return AGV_FE_ERR_LEVEL;
    size_t n_columns = (size_t)agv_fe_get_le(p + 36, 2);
    if (n != AGV_FE_ESTIMATE_HEADER_SIZE + 8 * n_columns) return AGV_FE_ERR_SIZE;
    if (n_columns > AGV_FE_N_COLUMNS && p[5] <= AGV_FE_ESTIMATE_REVISION) return AGV_FE_ERR_SIZE;
    e->revision = p[5];
    e->flags = p[6];
    e->level = p[7];
    e->seq = agv_fe_get_le(p + 8, 8);
    e->timestamp_ns = (int64_t)agv_fe_get_le(p + 16, 8);
    memcpy(e->gain_version, p + 24, 12);
    e->gain_version[12] = '\0';
    for (size_t i = 0; i < AGV_FE_N_COLUMNS; i++) {
        e->values[i] = i < n_columns ? agv_fe_bits_double(agv_fe_get_le(p + AGV_FE_ESTIMATE_HEADER_SIZE + 8 * i, 8))
                                     : agv_fe_bits_double(0x7ff8000000000000ull); /* NaN */
    }
    return 0;
}

#endif /* AGV_FE_ESTIMATE_H */
