// A user C module of the qemu build only (tools/firmware/test_qemu.sh): the HAL port the qemu
// suite's bridge benchmark runs the firmware on, written in C as machine.UART and
// machine.Pin are on the board.
//
// Why C: the benchmark reports the firmware's instructions, so the stand-in port's own
// cost is measured and taken out. Python stand-ins cost 800-3 000 instructions a call
// and, through MicroPython's map-lookup cache, a different amount in the benchmark
// than in the loop that calibrates them, so the firmware's figure came out as a small
// difference of two large, wandering numbers. A C method costs a few hundred
// instructions, always the same.
//
//   port = memport.Port(counts)   counts: array('i') of call counters shared by ports
//                                 (index: the K_* constants below, as qemu_suite's H_*;
//                                 the last counts the bytes queued)
//   port.load(data, n, off=0, hold=0)
//                                 data[off:off + n] becomes the bytes waiting (anything
//                                 unread is dropped); they show after `hold` calls of
//                                 any() that return 0 (a reply after its request)
//   port.trickle(k)               any()/readinto give at most k bytes (0: all): with
//                                 k = 1 every byte arrives on its own pass
//   port.any(), port.readinto(buf, n), port.write(buf, off, n), port.queue(buf, off, n),
//   port.drain(), port.de(v), port.sleep_us(us)   the HAL calls, each counted
//   port.writes, port.tx_bytes    frames sent (pieces ending in 0xEE), bytes sent
#include <string.h>
#include "py/runtime.h"

#define RX_SIZE (512)

// K_QBYTES: bytes queued (not a call: what queue calls carried, for pricing them).
enum { K_ANY, K_READ, K_WRITE, K_DE, K_SLEEP, K_LOAD, K_QUEUE, K_DRAIN, K_QBYTES, K_COUNT };

typedef struct {
    mp_obj_base_t base;
    mp_obj_t counts_obj;  // keeps the counters' array alive
    int32_t *counts;
    size_t rx_n;
    size_t rx_pos;
    size_t hold;
    size_t trickle;
    mp_int_t writes;
    mp_int_t tx_bytes;
    uint8_t rx[RX_SIZE];
} memport_obj_t;

static memport_obj_t *port_of(mp_obj_t self_in, int k) {
    memport_obj_t *self = MP_OBJ_TO_PTR(self_in);
    self->counts[k] += 1;
    return self;
}

static size_t waiting(memport_obj_t *self) {
    size_t k = self->rx_n - self->rx_pos;
    if (self->trickle != 0 && k > self->trickle) {
        k = self->trickle;
    }
    return k;
}

static mp_obj_t memport_make_new(const mp_obj_type_t *type, size_t n_args, size_t n_kw, const mp_obj_t *args) {
    mp_arg_check_num(n_args, n_kw, 1, 1, false);
    mp_buffer_info_t info;
    mp_get_buffer_raise(args[0], &info, MP_BUFFER_RW);
    if (info.typecode != 'i' || info.len < K_COUNT * sizeof(int32_t)) {
        mp_raise_ValueError(MP_ERROR_TEXT("counts: array('i') of 9"));
    }
    memport_obj_t *self = mp_obj_malloc(memport_obj_t, type);
    self->counts_obj = args[0];  // (an array is never resized here: the pointer stays valid)
    self->counts = info.buf;
    self->rx_n = 0;
    self->rx_pos = 0;
    self->hold = 0;
    self->trickle = 0;
    self->writes = 0;
    self->tx_bytes = 0;
    return MP_OBJ_FROM_PTR(self);
}

static mp_obj_t memport_load(size_t n_args, const mp_obj_t *args) {
    memport_obj_t *self = port_of(args[0], K_LOAD);
    mp_buffer_info_t info;
    mp_get_buffer_raise(args[1], &info, MP_BUFFER_READ);
    mp_int_t n = mp_obj_get_int(args[2]);
    mp_int_t off = n_args > 3 ? mp_obj_get_int(args[3]) : 0;
    mp_int_t hold = n_args > 4 ? mp_obj_get_int(args[4]) : 0;
    if (off < 0 || n < 0 || hold < 0 || n > RX_SIZE || (size_t)off > info.len || (size_t)n > info.len - (size_t)off) {
        mp_raise_ValueError(MP_ERROR_TEXT("load: range"));
    }
    memcpy(self->rx, (const uint8_t *)info.buf + off, n);
    self->rx_n = n;
    self->rx_pos = 0;
    self->hold = hold;
    return mp_const_none;
}
static MP_DEFINE_CONST_FUN_OBJ_VAR_BETWEEN(memport_load_obj, 3, 5, memport_load);

static mp_obj_t memport_trickle(mp_obj_t self_in, mp_obj_t k_in) {
    memport_obj_t *self = MP_OBJ_TO_PTR(self_in);
    self->trickle = mp_obj_get_int(k_in);
    return mp_const_none;
}
static MP_DEFINE_CONST_FUN_OBJ_2(memport_trickle_obj, memport_trickle);

static mp_obj_t memport_any(mp_obj_t self_in) {
    memport_obj_t *self = port_of(self_in, K_ANY);
    if (self->hold != 0) {
        self->hold -= 1;
        return MP_OBJ_NEW_SMALL_INT(0);
    }
    return MP_OBJ_NEW_SMALL_INT(waiting(self));
}
static MP_DEFINE_CONST_FUN_OBJ_1(memport_any_obj, memport_any);

static mp_obj_t memport_readinto(mp_obj_t self_in, mp_obj_t buf_in, mp_obj_t n_in) {
    memport_obj_t *self = port_of(self_in, K_READ);
    mp_buffer_info_t info;
    mp_get_buffer_raise(buf_in, &info, MP_BUFFER_WRITE);
    size_t n = mp_obj_get_int(n_in);
    size_t k = self->hold != 0 ? 0 : waiting(self);
    if (k > n) {
        k = n;
    }
    if (k > info.len) {
        k = info.len;
    }
    memcpy(info.buf, self->rx + self->rx_pos, k);
    self->rx_pos += k;
    return MP_OBJ_NEW_SMALL_INT(k);
}
static MP_DEFINE_CONST_FUN_OBJ_3(memport_readinto_obj, memport_readinto);

// write and queue: the bytes are counted, not kept (the benchmark checks frames by
// their count; the host tests check the bytes).
static mp_int_t sent(memport_obj_t *self, const mp_obj_t *args) {
    mp_buffer_info_t info;
    mp_get_buffer_raise(args[1], &info, MP_BUFFER_READ);
    mp_int_t off = mp_obj_get_int(args[2]);
    mp_int_t n = mp_obj_get_int(args[3]);
    if (off < 0 || n <= 0 || (size_t)(off + n) > info.len) {
        mp_raise_ValueError(MP_ERROR_TEXT("write: range"));
    }
    self->tx_bytes += n;
    if (((const uint8_t *)info.buf)[off + n - 1] == 0xEE) {
        self->writes += 1;
    }
    return n;
}

static mp_obj_t memport_write(size_t n_args, const mp_obj_t *args) {
    (void)n_args;
    sent(port_of(args[0], K_WRITE), args);
    return mp_const_none;
}
static MP_DEFINE_CONST_FUN_OBJ_VAR_BETWEEN(memport_write_obj, 4, 4, memport_write);

static mp_obj_t memport_queue(size_t n_args, const mp_obj_t *args) {
    (void)n_args;
    memport_obj_t *self = port_of(args[0], K_QUEUE);
    mp_int_t n = sent(self, args);
    self->counts[K_QBYTES] += n;
    return MP_OBJ_NEW_SMALL_INT(n);
}
static MP_DEFINE_CONST_FUN_OBJ_VAR_BETWEEN(memport_queue_obj, 4, 4, memport_queue);

static mp_obj_t memport_drain(mp_obj_t self_in) {
    port_of(self_in, K_DRAIN);
    return MP_OBJ_NEW_SMALL_INT(0);
}
static MP_DEFINE_CONST_FUN_OBJ_1(memport_drain_obj, memport_drain);

static mp_obj_t memport_de(mp_obj_t self_in, mp_obj_t v_in) {
    (void)v_in;
    port_of(self_in, K_DE);
    return mp_const_none;
}
static MP_DEFINE_CONST_FUN_OBJ_2(memport_de_obj, memport_de);

// DE delays are waiting, not work: a sleep is counted and returns at once.
static mp_obj_t memport_sleep_us(mp_obj_t self_in, mp_obj_t us_in) {
    (void)us_in;
    port_of(self_in, K_SLEEP);
    return mp_const_none;
}
static MP_DEFINE_CONST_FUN_OBJ_2(memport_sleep_us_obj, memport_sleep_us);

static void memport_attr(mp_obj_t self_in, qstr attr, mp_obj_t *dest) {
    memport_obj_t *self = MP_OBJ_TO_PTR(self_in);
    if (dest[0] == MP_OBJ_NULL && attr == MP_QSTR_writes) {
        dest[0] = mp_obj_new_int(self->writes);
    } else if (dest[0] == MP_OBJ_NULL && attr == MP_QSTR_tx_bytes) {
        dest[0] = mp_obj_new_int(self->tx_bytes);
    } else {
        dest[1] = MP_OBJ_SENTINEL;  // methods: from the locals dict
    }
}

static const mp_rom_map_elem_t memport_locals_dict_table[] = {
    { MP_ROM_QSTR(MP_QSTR_load), MP_ROM_PTR(&memport_load_obj) },
    { MP_ROM_QSTR(MP_QSTR_trickle), MP_ROM_PTR(&memport_trickle_obj) },
    { MP_ROM_QSTR(MP_QSTR_any), MP_ROM_PTR(&memport_any_obj) },
    { MP_ROM_QSTR(MP_QSTR_readinto), MP_ROM_PTR(&memport_readinto_obj) },
    { MP_ROM_QSTR(MP_QSTR_write), MP_ROM_PTR(&memport_write_obj) },
    { MP_ROM_QSTR(MP_QSTR_queue), MP_ROM_PTR(&memport_queue_obj) },
    { MP_ROM_QSTR(MP_QSTR_drain), MP_ROM_PTR(&memport_drain_obj) },
    { MP_ROM_QSTR(MP_QSTR_de), MP_ROM_PTR(&memport_de_obj) },
    { MP_ROM_QSTR(MP_QSTR_sleep_us), MP_ROM_PTR(&memport_sleep_us_obj) },
};
static MP_DEFINE_CONST_DICT(memport_locals_dict, memport_locals_dict_table);

MP_DEFINE_CONST_OBJ_TYPE(
    memport_type_Port,
    MP_QSTR_Port,
    MP_TYPE_FLAG_NONE,
    make_new, memport_make_new,
    attr, memport_attr,
    locals_dict, &memport_locals_dict
    );

static const mp_rom_map_elem_t memport_module_globals_table[] = {
    { MP_ROM_QSTR(MP_QSTR___name__), MP_ROM_QSTR(MP_QSTR_memport) },
    { MP_ROM_QSTR(MP_QSTR_Port), MP_ROM_PTR(&memport_type_Port) },
};
static MP_DEFINE_CONST_DICT(memport_module_globals, memport_module_globals_table);

const mp_obj_module_t memport_module = {
    .base = { &mp_type_module },
    .globals = (mp_obj_dict_t *)&memport_module_globals,
};

MP_REGISTER_MODULE(MP_QSTR_memport, memport_module);
