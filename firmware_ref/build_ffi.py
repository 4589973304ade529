"""cffi build of the reference firmware as ``firmware_ref._capsheet_fw`` (out-of-line API mode), and
of its mutant test build ``firmware_ref._capsheet_fw_mutants`` (-DCAPSHEET_MUTANTS).

Built at install time through ``setup.py``'s ``cffi_modules`` (``pip install -e .``), or by hand
for development::

    .venv/bin/python firmware_ref/build_ffi.py      # writes firmware_ref/_capsheet_fw*.so

The C sources are compiled as they are (firmware_ref/src/*.c); the HAL callbacks are Python
functions (``extern "Python"``) that `firmware_ref.chip.CFirmwareChip` routes to its instance.
"""

from __future__ import annotations

import os
import shutil
import shlex
import sysconfig
from pathlib import Path

from cffi import FFI

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
#: the sensor drivers (firmware_ref/drivers/) built into both modules: one entry per .c file (a new
#: part's driver adds its file here and its declarations to DRIVERS_CDEF below)
DRIVER_SOURCES = [
    "drivers/icm42688p.c",
    "drivers/link_sensors.c",
    "drivers/mmc5983ma.c",
]
SOURCES = ["src/codec.c", "src/payload.c", "src/chip.c", "src/chip_imu.c"] + DRIVER_SOURCES


def _check_compiler() -> None:
    """Fail early, and say what to do, when there is no C compiler."""
    cc = os.environ.get("CC") or sysconfig.get_config_var("CC") or "cc"
    exe = shlex.split(cc)[0] if cc.strip() else "cc"
    if shutil.which(exe) is None:
        raise RuntimeError(
            f"capsheet: building the C reference firmware (firmware_ref/) needs a C compiler, and "
            f"'{exe}' was not found. Install one (Debian/Ubuntu: apt-get install gcc; macOS: "
            f"xcode-select --install) or point CC at it, then reinstall.")


CDEF = r"""
typedef struct {
    uint8_t axis; uint8_t flags; int16_t offset_q4; float sensitivity;
} capsheet_cal_t;

typedef struct {
    uint8_t type;
    uint16_t node;
    union {
        struct { uint64_t uid; } announce;
        struct { uint8_t fw_major, fw_minor, fw_patch, protocol_version; uint16_t capabilities;
                 uint8_t adc_bits, state; } info;
        struct { uint16_t counter; int16_t x, y, z; uint8_t status; } sample;
        struct { uint8_t state, flags, rx_errors, missed_syncs; uint32_t uptime_s; } status;
        struct { uint8_t command, detail; } ack;
        struct { uint8_t command, reason; } nack;
        capsheet_cal_t cal;
        struct { uint16_t counter, first_link; uint8_t count; const uint8_t *words; } snapshot;
        struct { uint8_t flags, sample_format; uint16_t first_link, link_count, sync_rate_hz; } gateway_info;
        struct { uint16_t counter; } sync;
        struct { uint16_t new_node, link; uint32_t uid_low; } assign;
        struct { uint16_t rate_hz; uint8_t range, filter; uint16_t heartbeat_ms; } config;
        struct { uint8_t axis; } cal_read;
        struct { uint8_t block, index, flags, reserved; float value; } cal_imu;
        struct { uint8_t block, index; } cal_imu_read;
        struct { uint16_t counter; int16_t x, y, z; uint8_t status; uint8_t format; int16_t time_us;
                 int16_t gx, gy, gz, mx, my, mz; } imu_sample;
        struct { uint16_t counter; int16_t gx, gy, gz; } imu_gyro;
        struct { uint16_t counter; int16_t mx, my, mz; } imu_mag;
        struct { uint8_t counter_lo; int16_t x, y, z; uint8_t status; int16_t time_us; } imu_accel;
        struct { uint16_t counter, first_link; uint8_t count, format; const uint8_t *records; } snapshot_imu;
        struct { uint8_t format, gyro_range, mag_range, flags; } config_imu;
    } u;
} capsheet_msg_t;

typedef struct {
    uint8_t *buf; size_t cap; size_t len; bool discarding; uint8_t version;
    uint32_t frames; uint32_t errors;
} capsheet_stream_t;

typedef struct { uint8_t reply; uint8_t next_state; uint8_t validate; } capsheet_rule_t;

typedef enum { CAPSHEET_CAN_AUTO = 0, CAPSHEET_CAN_CLASSIC = 1, CAPSHEET_CAN_FD = 2 } capsheet_can_mode_t;
typedef enum { CAPSHEET_TRANSPORT_SERIAL = 0, CAPSHEET_TRANSPORT_CAN = 1 } capsheet_transport_t;

typedef struct {
    int16_t gyro[3];
    int16_t mag[3];
    uint64_t latch_us;
    uint8_t status;
} capsheet_imu_reading_t;

typedef struct {
    void *user;
    int32_t (*read_axes)(void *user, uint64_t now_us, int16_t xyz[3], uint8_t *status);
    int32_t (*send_bytes)(void *user, const uint8_t *data, size_t len);
    int32_t (*send_can)(void *user, uint32_t id, const uint8_t *data, uint8_t len, bool is_fd);
    uint64_t (*read_uid)(void *user);
    int32_t (*cal_load)(void *user, uint8_t axis, capsheet_cal_t *cal);
    int32_t (*cal_store)(void *user, uint8_t axis, const capsheet_cal_t *cal);
    int32_t (*read_imu)(void *user, uint64_t now_us, uint8_t gyro_range, uint8_t mag_range,
                        bool want_mag, capsheet_imu_reading_t *out);
    int32_t (*cal_imu_load)(void *user, uint8_t element, uint32_t *bits);
    int32_t (*cal_imu_store)(void *user, uint8_t element, uint32_t bits);
} capsheet_hal_t;

typedef struct { capsheet_transport_t transport; bool can_fd; uint16_t capabilities; } capsheet_chip_config_t;

typedef struct {
    uint64_t uid;
    uint16_t node;
    uint16_t prev_node;
    bool has_prev;
    uint16_t link;
    bool has_link;
    uint8_t state;
    bool started;
    bool powered;
    uint8_t rx_errors;
    uint8_t missed_syncs;
    bool have_sync;
    uint16_t last_sync;
    uint32_t salt;
    uint8_t range_code;
    uint16_t heartbeat_ms;
    uint8_t imu_format;
    uint8_t gyro_range;
    uint8_t mag_range;
    uint8_t imu_flags;
    capsheet_cal_t cal[3];
    capsheet_stream_t rx;
    uint64_t boot_us;
    MUTANT_FIELDS
    ...;
} capsheet_chip_t;

#define CAPSHEET_PROTOCOL_VERSION ...
#define CAPSHEET_MAX_FRAME_SIZE ...
#define CAPSHEET_MAX_ENCODED_SIZE ...
#define CAPSHEET_MAX_WIRE_SIZE ...
#define CAPSHEET_MIN_RX_BUFFER_SIZE ...
#define CAPSHEET_RX_BUFFER_SIZE ...
#define CAPSHEET_CHIP_TX_WIRE_SIZE ...
#define CAPSHEET_FW_VERSION_MAJOR ...
#define CAPSHEET_FW_VERSION_MINOR ...
#define CAPSHEET_FW_VERSION_PATCH ...
#define CAPSHEET_CRC_INIT ...
#define CAPSHEET_STAY ...
#define CAPSHEET_IMU ...
#define CAPSHEET_TIME_UNKNOWN ...
#define CAPSHEET_CAP_GYRO ...
#define CAPSHEET_CAP_MAG ...
#define CAPSHEET_CAP_SAMPLE_TIME ...

uint16_t capsheet_crc16(const uint8_t *data, size_t len, uint16_t crc);
int32_t capsheet_cobs_encode(const uint8_t *in, size_t len, uint8_t *out, size_t cap);
int32_t capsheet_cobs_decode(const uint8_t *in, size_t len, uint8_t *out, size_t cap);
uint8_t capsheet_priority(uint8_t type);
bool capsheet_type_known(uint8_t type);
uint16_t capsheet_provisional_node(uint64_t uid, uint32_t salt);
int32_t capsheet_payload_encode(const capsheet_msg_t *msg, uint8_t *buf, size_t cap);
int32_t capsheet_payload_decode(uint8_t type, uint16_t node, const uint8_t *payload, size_t len,
                                capsheet_msg_t *out);
int32_t capsheet_serial_encode(const capsheet_msg_t *msg, uint8_t *out, size_t cap);
int32_t capsheet_serial_encode_raw(uint8_t version, uint8_t type, uint16_t node, const uint8_t *payload,
                                   size_t len, uint8_t *out, size_t cap);
int32_t capsheet_serial_decode_frame(uint8_t *frame, size_t len, capsheet_msg_t *out, uint8_t *version);
int32_t capsheet_stream_init(capsheet_stream_t *s, uint8_t *buf, size_t cap);
int32_t capsheet_stream_feed(capsheet_stream_t *s, uint8_t byte, capsheet_msg_t *out);
uint32_t capsheet_can_make_id(uint8_t priority, uint8_t type, uint8_t version, uint16_t node);
int32_t capsheet_can_encode(const capsheet_msg_t *msg, capsheet_can_mode_t mode, uint32_t *id,
                            uint8_t *data, size_t cap, bool *is_fd);
int32_t capsheet_can_fd_length(size_t n);
int32_t capsheet_can_decode(uint32_t id, bool is_extended, bool is_fd, const uint8_t *data, size_t len,
                            capsheet_msg_t *out, uint8_t *version);
int32_t capsheet_rule_for(uint8_t state, uint8_t type, capsheet_rule_t *rule);

int32_t capsheet_chip_init(capsheet_chip_t *chip, const capsheet_chip_config_t *config,
                           const capsheet_hal_t *hal, uint8_t *rx_buf, size_t rx_cap);
int32_t capsheet_chip_power_on(capsheet_chip_t *chip, uint64_t now_us);
int32_t capsheet_chip_rx_bytes(capsheet_chip_t *chip, const uint8_t *data, size_t len, uint64_t now_us);
int32_t capsheet_chip_rx_can(capsheet_chip_t *chip, uint32_t id, bool is_extended, bool is_fd,
                             const uint8_t *data, size_t len, uint64_t now_us);
int32_t capsheet_chip_poll(capsheet_chip_t *chip, uint64_t now_us);
void capsheet_chip_sensor_fault(capsheet_chip_t *chip);

extern "Python" int32_t capsheet_py_read_axes(void *, uint64_t, int16_t *, uint8_t *);
extern "Python" int32_t capsheet_py_send_bytes(void *, const uint8_t *, size_t);
extern "Python" int32_t capsheet_py_send_can(void *, uint32_t, const uint8_t *, uint8_t, bool);
extern "Python" uint64_t capsheet_py_read_uid(void *);
extern "Python" int32_t capsheet_py_cal_load(void *, uint8_t, capsheet_cal_t *);
extern "Python" int32_t capsheet_py_cal_store(void *, uint8_t, const capsheet_cal_t *);
extern "Python" int32_t capsheet_py_cal_imu_load(void *, uint8_t, uint32_t *);
extern "Python" int32_t capsheet_py_cal_imu_store(void *, uint8_t, uint32_t);
extern "Python" int32_t capsheet_py_read_imu(void *, uint64_t, uint8_t, uint8_t, bool, capsheet_imu_reading_t *);
"""


#: the declarations of firmware_ref/drivers/ (capsheet_bus.h, icm42688p.h, link_sensors.h, mmc5983ma.h): kept apart
#: from CDEF, which copies capsheet_fw.h alone (tests/firmware_ref/test_cdef.py). A new driver adds its
#: declarations at the end. The bus callbacks are Python (firmware_ref/sil_bus.py routes them).
DRIVERS_CDEF = r"""
typedef struct {
    void *user;
    int32_t (*spi_transfer)(void *user, uint8_t cs, const uint8_t *tx, uint8_t *rx, size_t len);
    int32_t (*i2c_write_read)(void *user, uint8_t addr7, const uint8_t *tx, size_t tx_len, uint8_t *rx, size_t rx_len);
    void (*delay_us)(void *user, uint32_t us);
} capsheet_bus_t;

typedef struct {
    uint8_t accel_fs_sel; uint8_t gyro_fs_sel; uint8_t odr; uint8_t ui_filt_bw; bool gyro_on;
} icm42688p_config_t;
typedef struct {
    int16_t temp; int16_t accel[3]; int16_t gyro[3]; bool fresh; bool saturated; bool latch_known;
    uint64_t latch_us;
} icm42688p_sample_t;
typedef struct {
    uint8_t cs; uint8_t phase; uint8_t self_test; bool config_dirty;
    icm42688p_config_t want; icm42688p_config_t cfg; int32_t error;
    int32_t st_off[3];
    ...;
} icm42688p_t;
#define ICM42688P_ERR_BUS ...
#define ICM42688P_ERR_WHO_AM_I ...
#define ICM42688P_ERR_RESET ...
#define ICM42688P_ERR_SELF_TEST ...
#define ICM42688P_ERR_GONE ...
#define ICM42688P_ERR_NOT_READY ...
#define ICM42688P_ERR_ARGUMENT ...
#define ICM42688P_ST_RAN ...
#define ICM42688P_ST_GYRO_PASS ...
#define ICM42688P_ST_ACCEL_PASS ...
void icm42688p_default_config(icm42688p_config_t *cfg);
int32_t icm42688p_init(icm42688p_t *d, const capsheet_bus_t *bus, uint8_t cs, bool self_test);
int32_t icm42688p_configure(icm42688p_t *d, const icm42688p_config_t *cfg);
int32_t icm42688p_step(icm42688p_t *d, uint64_t now_us);
int32_t icm42688p_run(icm42688p_t *d, uint64_t *now_us);
void icm42688p_data_ready(icm42688p_t *d, uint64_t edge_us);
int32_t icm42688p_read(icm42688p_t *d, uint64_t now_us, icm42688p_sample_t *out);
bool icm42688p_in_self_test(const icm42688p_t *d);
int32_t icm42688p_read_regs(icm42688p_t *d, uint8_t reg, uint8_t *buf, size_t len);
int32_t icm42688p_write_reg(icm42688p_t *d, uint8_t reg, uint8_t value);

typedef struct {
    void *ctx;
    int32_t (*poll)(void *ctx, uint64_t now_us);
    int32_t (*read)(void *ctx, uint64_t now_us, uint8_t mag_range, int16_t mag[3], uint8_t *status);
} capsheet_mag_driver_t;
typedef struct {
    icm42688p_t imu;
    const capsheet_mag_driver_t *mag;
    const capsheet_chip_t *chip;
    int16_t accel[3]; int16_t gyro[3]; uint64_t latch_us; uint8_t status; int32_t fault;
    ...;
} capsheet_link_sensors_t;
int32_t capsheet_link_sensors_init(capsheet_link_sensors_t *ls, const capsheet_bus_t *bus, uint8_t imu_cs,
                                   const capsheet_mag_driver_t *mag, const capsheet_chip_t *chip, bool self_test);
int32_t capsheet_link_sensors_poll(capsheet_link_sensors_t *ls, uint64_t now_us);
void capsheet_link_data_ready(capsheet_link_sensors_t *ls, uint64_t edge_us);
int32_t capsheet_link_read_axes(void *user, uint64_t now_us, int16_t xyz[3], uint8_t *status);
int32_t capsheet_link_read_imu(void *user, uint64_t now_us, uint8_t gyro_range, uint8_t mag_range,
                               bool want_mag, capsheet_imu_reading_t *out);

typedef struct {
    uint8_t cs; uint8_t i2c_addr; bool on_i2c; uint8_t bw; int8_t axes[3]; uint8_t phase; bool pending; int32_t error;
    int32_t offset2[3]; uint8_t tout; uint32_t measurements;
    ...;
} mmc5983ma_t;
#define MMC5983MA_ERR_BUS ...
#define MMC5983MA_ERR_PRODUCT_ID ...
#define MMC5983MA_ERR_OTP ...
#define MMC5983MA_ERR_SELF_TEST ...
#define MMC5983MA_ERR_TIMEOUT ...
#define MMC5983MA_ERR_GONE ...
#define MMC5983MA_ERR_NOT_READY ...
#define MMC5983MA_ERR_ARGUMENT ...
int32_t mmc5983ma_init(mmc5983ma_t *d, const capsheet_bus_t *bus, uint8_t cs, uint8_t bw);
int32_t mmc5983ma_init_i2c(mmc5983ma_t *d, const capsheet_bus_t *bus, uint8_t addr7, uint8_t bw);
int32_t mmc5983ma_set_axes(mmc5983ma_t *d, const int8_t axes[3]);
int32_t mmc5983ma_step(mmc5983ma_t *d, uint64_t now_us);
int32_t mmc5983ma_run(mmc5983ma_t *d, uint64_t *now_us);
int32_t mmc5983ma_read(mmc5983ma_t *d, uint64_t now_us, uint8_t mag_range, int16_t mag[3], uint8_t *status,
                       uint64_t *latch_us);
int32_t mmc5983ma_temperature_dc(const mmc5983ma_t *d);
void mmc5983ma_mag_driver(mmc5983ma_t *d, capsheet_mag_driver_t *out);
int32_t mmc5983ma_read_regs(mmc5983ma_t *d, uint8_t reg, uint8_t *buf, size_t len);
int32_t mmc5983ma_write_reg(mmc5983ma_t *d, uint8_t reg, uint8_t value);

extern "Python" int32_t capsheet_py_spi_transfer(void *, uint8_t, const uint8_t *, uint8_t *, size_t);
extern "Python" int32_t capsheet_py_i2c_write_read(void *, uint8_t, const uint8_t *, size_t, uint8_t *, size_t);
extern "Python" void capsheet_py_delay_us(void *, uint32_t);
extern "Python" int32_t capsheet_py_part_read_axes(void *, uint64_t, int16_t *, uint8_t *);
extern "Python" int32_t capsheet_py_part_read_imu(void *, uint64_t, uint8_t, uint8_t, bool, capsheet_imu_reading_t *);
"""


def _rel(path: Path) -> str:
    # setuptools wants sources relative to the project root (the cwd of a build).
    try:
        return os.path.relpath(path, os.getcwd())
    except ValueError:  # another drive (Windows)
        return str(path)


_check_compiler()


def _mutant_enum() -> str:
    """``capsheet_mutant_t`` as cffi declares it: the names from the header, the values from C."""
    import re
    names = re.findall(r"^\s*(CAPSHEET_MUT_[A-Z0-9_]+)", (HERE / "include" / "capsheet_fw.h").read_text(), re.M)
    return "typedef enum { " + ", ".join(names) + ", ... } capsheet_mutant_t;\n"


def _builder(module: str, mutants: bool) -> FFI:
    ffi = FFI()
    ffi.cdef(_mutant_enum() + CDEF.replace("MUTANT_FIELDS", "int32_t mutant;" if mutants else "") + DRIVERS_CDEF)
    ffi.set_source(
        module,
        '#include "capsheet_fw.h"\n#include "link_sensors.h"\n#include "mmc5983ma.h"\n',
        sources=[_rel(HERE / s) for s in SOURCES],
        include_dirs=[_rel(HERE / "include"), _rel(HERE / "drivers")],
        define_macros=[("CAPSHEET_MUTANTS", "1")] if mutants else [],
        extra_compile_args=["-O2"] if os.name != "nt" else [],
    )
    return ffi


#: the firmware as a chip vendor builds it
ffibuilder = _builder("firmware_ref._capsheet_fw", mutants=False)
#: a test build: the same sources with -DCAPSHEET_MUTANTS, each chip breaking the rule its
#: ``mutant`` field names (capsheet_fw.h; tests/host/conformance/mutants.py)
ffibuilder_mutants = _builder("firmware_ref._capsheet_fw_mutants", mutants=True)

if __name__ == "__main__":
    ffibuilder.compile(tmpdir=str(ROOT), verbose=False)
    ffibuilder_mutants.compile(tmpdir=str(ROOT), verbose=False)
