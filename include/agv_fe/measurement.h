/*
 * agv_fe/measurement.h - the vehicle side of the AGV fault estimator's wire protocol, version 1, in C99.
 *
 * What docs/protocol.md specifies and agv_protocol/wire.py implements, for a vehicle written in C: the 64-byte
 * measurement header followed by the vehicle id (all fields little-endian), the CRC-32 shard bucket of a vehicle
 * id, and the key expressions. Header only, no allocation, no dependency beyond the C standard library; any Zenoh
 * binding (zenoh-c, zenoh-pico) puts the encoded bytes on agv_fe_vehicle_key(..., "meas") with congestion control
 * BLOCK. The encoder writes every field byte by byte, so it is right on any host's endianness; the packed struct
 * describes the layout (and equals the bytes on a little-endian host).
 */
#ifndef AGV_FE_MEASUREMENT_H
#define AGV_FE_MEASUREMENT_H

#include <stddef.h>
#include <stdint.h>
#include <stdio.h>
#include <string.h>

#define AGV_FE_PROTOCOL_VERSION 1
#define AGV_FE_DEFAULT_PREFIX "agv"
#define AGV_FE_N_BUCKETS 16u
#define AGV_FE_HEADER_SIZE 64u
#define AGV_FE_MAX_ID_LEN 64u
/* the largest measurement: header and a 64-byte id */
#define AGV_FE_MAX_MEASUREMENT_SIZE (AGV_FE_HEADER_SIZE + AGV_FE_MAX_ID_LEN)
/* flag bit 0: the vehicle restarted its sequence (seq may jump back); bit 1: bytes 56-63 carry the road grade;
 * every other bit must be zero */
#define AGV_FE_FLAG_SEQUENCE_RESTART 0x01u
#define AGV_FE_FLAG_ROAD_GRADE 0x02u
#define AGV_FE_KNOWN_FLAGS (AGV_FE_FLAG_SEQUENCE_RESTART | AGV_FE_FLAG_ROAD_GRADE)

/* errors: the functions return these (negative) or a length / zero on success */
#define AGV_FE_ERR_ID (-1)        /* vehicle id not 1..64 of A-Z a-z 0-9 _ . - */
#define AGV_FE_ERR_SPACE (-2)     /* output buffer too small */
#define AGV_FE_ERR_SIZE (-3)      /* payload too short, or its length does not match the header's id length */
#define AGV_FE_ERR_MAGIC (-4)     /* not "AGVM" */
#define AGV_FE_ERR_VERSION (-5)   /* a format version this side does not speak */
#define AGV_FE_ERR_RESERVED (-6)  /* an unknown flag bit, or non-zero bytes 56-63 without flag bit 1 */

#if defined(_MSC_VER)
#pragma pack(push, 1)
#define AGV_FE_PACKED
#else
#define AGV_FE_PACKED __attribute__((packed))
#endif
/* The 64-byte header as it lies on the wire (little-endian); the vehicle id's L bytes follow it. */
struct AGV_FE_PACKED agv_fe_measurement_header {
    char magic[4];          /*  0: "AGVM" */
    uint8_t version;        /*  4: 1 */
    uint8_t flags;          /*  5: bit 0 = sequence restart, bit 1 = road grade, others 0 */
    uint16_t id_len;        /*  6: L, 1..64 */
    uint64_t seq;           /*  8: +1 per sample */
    int64_t timestamp_ns;   /* 16: ns since the Unix epoch, vehicle clock */
    double vx_mps;          /* 24: v_x [m/s], measured, + forward */
    double r_radps;         /* 32: yaw rate r [rad/s], measured, + left */
    double torque_nm;       /* 40: demanded total drive torque at the driven wheels T_d [N m], + driving */
    double steer_rad;       /* 48: demanded road-wheel angle delta_d [rad], + left */
    double grade_rad;       /* 56: road grade [rad], + uphill, with flag bit 1; zero bytes without it */
};
#if defined(_MSC_VER)
#pragma pack(pop)
#endif
typedef char agv_fe_header_is_64_bytes[sizeof(struct agv_fe_measurement_header) == AGV_FE_HEADER_SIZE ? 1 : -1];

/* One sample, as the encoder takes it and the decoder gives it. */
typedef struct {
    char vehicle_id[AGV_FE_MAX_ID_LEN + 1]; /* NUL-terminated */
    uint8_t flags;
    uint64_t seq;
    int64_t timestamp_ns;
    double vx_mps, r_radps, torque_nm, steer_rad;
    double grade_rad; /* sent with flag bit AGV_FE_FLAG_ROAD_GRADE only; 0 when decoded without it */
} agv_fe_measurement;

/* CRC-32 of zlib, ISO-HDLC (polynomial 0x04C11DB7 reflected = 0xEDB88320, initial and final XOR 0xFFFFFFFF). */
static inline uint32_t agv_fe_crc32(const uint8_t *data, size_t n) {
    uint32_t crc = 0xFFFFFFFFu;
    for (size_t i = 0; i < n; i++) {
        crc ^= data[i];
        for (int bit = 0; bit < 8; bit++) crc = (crc >> 1) ^ (0xEDB88320u & (0u - (crc & 1u)));
    }
    return crc ^ 0xFFFFFFFFu;
}

/* 1 if id is a valid vehicle id: 1 to 64 characters of A-Z a-z 0-9 _ . - */
static inline int agv_fe_valid_id(const char *id) {
    size_t n = 0;
    for (; id[n] != '\0'; n++) {
        char c = id[n];
        int ok = (c >= 'A' && c <= 'Z') || (c >= 'a' && c <= 'z') || (c >= '0' && c <= '9') || c == '_' ||
                 c == '.' || c == '-';
        if (!ok || n >= AGV_FE_MAX_ID_LEN) return 0;
    }
    return n >= 1;
}

/* The shard bucket "bXX": crc32 of the id's bytes mod 16 in two hex digits ("truck-7" -> "b0f"). out: 4 bytes. */
static inline int agv_fe_bucket(const char *id, char out[4]) {
    if (!agv_fe_valid_id(id)) return AGV_FE_ERR_ID;
    snprintf(out, 4, "b%02x", (unsigned)(agv_fe_crc32((const uint8_t *)id, strlen(id)) % AGV_FE_N_BUCKETS));
    return 0;
}

/* "{prefix}/v1/{bucket}/{id}/{kind}", kind one of meas, estimate, alarm, truth, alive. Returns its length. */
static inline int agv_fe_vehicle_key(char *out, size_t cap, const char *prefix, const char *id, const char *kind) {
    char bucket[4];
    if (agv_fe_bucket(id, bucket) != 0) return AGV_FE_ERR_ID;
    int n = snprintf(out, cap, "%s/v%d/%s/%s/%s", prefix, AGV_FE_PROTOCOL_VERSION, bucket, id, kind);
    return (n < 0 || (size_t)n >= cap) ? AGV_FE_ERR_SPACE : n;
}

static inline void agv_fe_put_le(uint8_t *p, uint64_t v, int bytes) {
    for (int i = 0; i < bytes; i++) p[i] = (uint8_t)(v >> (8 * i));
}

static inline uint64_t agv_fe_get_le(const uint8_t *p, int bytes) {
    uint64_t v = 0;
    for (int i = 0; i < bytes; i++) v |= (uint64_t)p[i] << (8 * i);
    return v;
}

static inline uint64_t agv_fe_double_bits(double d) {
    uint64_t bits;
    memcpy(&bits, &d, sizeof bits);
    return bits;
}

static inline double agv_fe_bits_double(uint64_t bits) {
    double d;
    memcpy(&d, &bits, sizeof d);
    return d;
}

/* Encode m into out (at least 64 + strlen(id) bytes); returns the payload's length. */
static inline int agv_fe_encode(const agv_fe_measurement *m, uint8_t *out, size_t cap) {
    if (!agv_fe_valid_id(m->vehicle_id)) return AGV_FE_ERR_ID;
    size_t id_len = strlen(m->vehicle_id);
    if (cap < AGV_FE_HEADER_SIZE + id_len) return AGV_FE_ERR_SPACE;
    memcpy(out, "AGVM", 4);
    out[4] = AGV_FE_PROTOCOL_VERSION;
    out[5] = m->flags;
    agv_fe_put_le(out + 6, id_len, 2);
    agv_fe_put_le(out + 8, m->seq, 8);
    agv_fe_put_le(out + 16, (uint64_t)m->timestamp_ns, 8);
    agv_fe_put_le(out + 24, agv_fe_double_bits(m->vx_mps), 8);
    agv_fe_put_le(out + 32, agv_fe_double_bits(m->r_radps), 8);
    agv_fe_put_le(out + 40, agv_fe_double_bits(m->torque_nm), 8);
    agv_fe_put_le(out + 48, agv_fe_double_bits(m->steer_rad), 8);
    if (m->flags & AGV_FE_FLAG_ROAD_GRADE)
        agv_fe_put_le(out + 56, agv_fe_double_bits(m->grade_rad), 8);
    else
        memset(out + 56, 0, 8);
    memcpy(out + AGV_FE_HEADER_SIZE, m->vehicle_id, id_len);
    return (int)(AGV_FE_HEADER_SIZE + id_len);
}

/* Decode a payload with the service's checks (size, magic, version, flags and reserved bytes, id). */
static inline int agv_fe_decode(const uint8_t *p, size_t n, agv_fe_measurement *m) {
    if (n < AGV_FE_HEADER_SIZE) return AGV_FE_ERR_SIZE;
    if (memcmp(p, "AGVM", 4) != 0) return AGV_FE_ERR_MAGIC;
    if (p[4] != AGV_FE_PROTOCOL_VERSION) return AGV_FE_ERR_VERSION;
    size_t id_len = (size_t)agv_fe_get_le(p + 6, 2);
    if (n != AGV_FE_HEADER_SIZE + id_len || id_len > AGV_FE_MAX_ID_LEN) return AGV_FE_ERR_SIZE;
    int graded = (p[5] & AGV_FE_FLAG_ROAD_GRADE) != 0;
    if ((p[5] & ~AGV_FE_KNOWN_FLAGS) != 0 || (!graded && agv_fe_get_le(p + 56, 8) != 0)) return AGV_FE_ERR_RESERVED;
    memcpy(m->vehicle_id, p + AGV_FE_HEADER_SIZE, id_len);
    m->vehicle_id[id_len] = '\0';
    if (strlen(m->vehicle_id) != id_len || !agv_fe_valid_id(m->vehicle_id)) return AGV_FE_ERR_ID;
    m->flags = p[5];
    m->seq = agv_fe_get_le(p + 8, 8);
    m->timestamp_ns = (int64_t)agv_fe_get_le(p + 16, 8);
    m->vx_mps = agv_fe_bits_double(agv_fe_get_le(p + 24, 8));
    m->r_radps = agv_fe_bits_double(agv_fe_get_le(p + 32, 8));
    m->torque_nm = agv_fe_bits_double(agv_fe_get_le(p + 40, 8));
    m->steer_rad = agv_fe_bits_double(agv_fe_get_le(p + 48, 8));
    m->grade_rad = graded ? agv_fe_bits_double(agv_fe_get_le(p + 56, 8)) : 0.0;
    return 0;
}

#endif /* AGV_FE_MEASUREMENT_H */
