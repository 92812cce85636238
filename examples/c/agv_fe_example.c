/*
 * A vehicle's measurement in C with include/agv_fe/measurement.h: encode one sample, print its key expression and
 * its bytes in hex; or decode a payload given in hex. What a vehicle would put with any Zenoh binding:
 *
 *   cc -std=c99 -Wall -Wextra -pedantic -I include examples/c/agv_fe_example.c -o agv_fe_example
 *   ./agv_fe_example encode truck-7 42 1700000000420000000 10.5 0.01 120 0.002
 *   ./agv_fe_example decode 4147564d...
 *   ./agv_fe_example decode-estimate 41475645...   (a binary estimate received on ".../estimate.bin")
 */
#include <stdlib.h>

#include "agv_fe/estimate.h"
#include "agv_fe/measurement.h"

static int encode(int argc, char **argv) {
    if (argc != 9 && argc != 10) {
        fprintf(stderr, "usage: encode ID SEQ T_NS VX R TORQUE STEER [GRADE]\n");
        return 2;
    }
    agv_fe_measurement m;
    memset(&m, 0, sizeof m);
    if (strlen(argv[2]) > AGV_FE_MAX_ID_LEN) {
        fprintf(stderr, "invalid vehicle id\n");
        return 1;
    }
    strcpy(m.vehicle_id, argv[2]);
    m.seq = strtoull(argv[3], NULL, 10);
    m.timestamp_ns = strtoll(argv[4], NULL, 10);
    m.vx_mps = strtod(argv[5], NULL);
    m.r_radps = strtod(argv[6], NULL);
    m.torque_nm = strtod(argv[7], NULL);
    m.steer_rad = strtod(argv[8], NULL);
    m.flags = m.seq == 0 ? AGV_FE_FLAG_SEQUENCE_RESTART : 0;
    if (argc == 10) { /* the road grade [rad], + uphill */
        m.grade_rad = strtod(argv[9], NULL);
        m.flags |= AGV_FE_FLAG_ROAD_GRADE;
    }
    uint8_t payload[AGV_FE_MAX_MEASUREMENT_SIZE];
    char key[160];
    int n = agv_fe_encode(&m, payload, sizeof payload);
    if (n < 0 || agv_fe_vehicle_key(key, sizeof key, AGV_FE_DEFAULT_PREFIX, m.vehicle_id, "meas") < 0) {
        fprintf(stderr, "invalid vehicle id (error %d)\n", n);
        return 1;
    }
    printf("%s\n", key);
    for (int i = 0; i < n; i++) printf("%02x", payload[i]);
    printf("\n");
    return 0;
}

static int hex_bytes(const char *hex, uint8_t *out, size_t cap, size_t *n) {
    *n = strlen(hex) / 2;
    if (strlen(hex) % 2 != 0 || *n > cap) {
        fprintf(stderr, "expected at most %zu bytes in hex\n", cap);
        return 2;
    }
    for (size_t i = 0; i < *n; i++) {
        unsigned byte;
        if (sscanf(hex + 2 * i, "%2x", &byte) != 1) return 2;
        out[i] = (uint8_t)byte;
    }
    return 0;
}

static int decode(const char *hex) {
    uint8_t payload[AGV_FE_MAX_MEASUREMENT_SIZE + 1];
    size_t n;
    if (hex_bytes(hex, payload, sizeof payload, &n) != 0) return 2;
    agv_fe_measurement m;
    int error = agv_fe_decode(payload, n, &m);
    if (error != 0) {
        printf("error %d\n", error);
        return 1;
    }
    printf("%s %u %llu %lld %.17g %.17g %.17g %.17g", m.vehicle_id, (unsigned)m.flags, (unsigned long long)m.seq,
           (long long)m.timestamp_ns, m.vx_mps, m.r_radps, m.torque_nm, m.steer_rad);
    if (m.flags & AGV_FE_FLAG_ROAD_GRADE) printf(" %.17g", m.grade_rad);
    printf("\n");
    return 0;
}

static int decode_estimate(const char *hex) {
    uint8_t payload[AGV_FE_ESTIMATE_HEADER_SIZE + 8 * 64];
    size_t n;
    if (hex_bytes(hex, payload, sizeof payload, &n) != 0) return 2;
    agv_fe_estimate e;
    int error = agv_fe_decode_estimate(payload, n, &e);
    if (error != 0) {
        printf("error %d\n", error);
        return 1;
    }
    printf("%u %u %u %llu %lld %s", (unsigned)e.revision, (unsigned)e.flags, (unsigned)e.level,
           (unsigned long long)e.seq, (long long)e.timestamp_ns, e.gain_version);
    for (int i = 0; i < AGV_FE_N_COLUMNS; i++) printf(" %.17g", e.values[i]);
    printf("\n");
    return 0;
}

int main(int argc, char **argv) {
    if (argc >= 2 && strcmp(argv[1], "encode") == 0) return encode(argc, argv);
    if (argc == 3 && strcmp(argv[1], "decode") == 0) return decode(argv[2]);
    if (argc == 3 && strcmp(argv[1], "decode-estimate") == 0) return decode_estimate(argv[2]);
    fprintf(stderr, "usage: %s encode ID SEQ T_NS VX R TORQUE STEER [GRADE] | decode HEX | decode-estimate HEX\n", argv[0]);
    return 2;
}
