// A user C module of the qemu build only (tools/firmware/test_qemu.sh): the board's CAN port
// (machine.CAN on FDCAN1) and its third USB CDC port, for tools/firmware/qemu/can_suite.py.
//
// memcan.CAN is a model of what the board's C does for each call jig.canport makes,
// written for this project from MicroPython v1.28's extmod/machine_can.c and
// ports/stm32/{machine_can,fdcan}.c (read, not copied): the same Python-facing work
// (mp_arg_parse_all with send's keyword table, the buffer protocol, the list and its
// memoryview filled in place, a real mp_irq object whose flags() asks the port) and
// the same controller work on registers and a message RAM that are plain memory here
// (the RX FIFO's get index and element, the DLC table, the scan of the 16 TX buffers
// and of the finished ones, the interrupt enables the HAL sets). Its instructions are
// kept in the figures as the board's price of those calls.
//
// The interrupt: the rig's bus_rx()/bus_tx_done() play the controller (an element
// into the RX FIFO, a TX buffer finished; not board work) and then run the interrupt
// service routine model: IR & IE, the RX interrupt masked until recv() re-enables it,
// and the handler called as a hard IRQ by MicroPython's own mp_irq_handler
// (shared/runtime/mpirq.c, compiled in by mpirq_inc.c: scheduler and GC locked, nlr).
// bus_put() does only the controller's part, so the suite can take it out.
//
//   can = memcan.CAN()                 opened and started (hal.can_open's result)
//   can.irq(handler, trigger, hard), recv(lst), send(id, data, flags=0), state(),
//   get_counters(lst), set_filters(f), restart(), deinit()   as machine.CAN
//   can.bus_rx(id, data, n, flags)     a frame received (flags: machine.CAN's), then the ISR
//   can.bus_put(id, data, n, flags)    the same without the ISR (the rig's own share)
//   can.bus_clear()                    empty the RX FIFO (after bus_put)
//   can.bus_tx_done(ok)                the pending TX buffers finish, then the ISR
//   can.bus_nop(x)                     a rig call that does nothing (its call's share)
//   can.sent, can.last_id, can.last_len, can.isr_runs, can.rx_fill   for the checks
//
//   vcp = memcan.Vcp(counts)           the SLCAN port (pyb.USB_VCP's any/readinto/write);
//                                      counts: array('i') of 4, calls counted per kind
//   vcp.load(data, n)                  the host's bytes waiting (a line); vcp.again() rewinds
//   vcp.taken                          bytes the port took from write()
#include <string.h>
#include "py/runtime.h"
#include "py/mperrno.h"
#include "py/objarray.h"
#include "py/objlist.h"
#include "shared/runtime/mpirq.h"

// machine.CAN's constants (v1.28)
#define FLAG_RTR (1)
#define FLAG_EXT_ID (2)
#define IRQ_TX (1)
#define IRQ_RX (2)
#define IRQ_TX_FAILED (4)
#define IRQ_STATE (8)
#define IRQ_IDX_SHIFT (16)
#define RECV_ERR_OVERRUN (2)

// Register bits, FDCAN's layout where it matters (IR/IE bit numbers, element words)
#define IT_RF0N (1u << 0)   // RX FIFO 0 new message
#define IT_RF0F (1u << 2)   // RX FIFO 0 full
#define IT_RF0L (1u << 3)   // RX FIFO 0 message lost
#define IT_RF1N (1u << 4)
#define IT_RF1F (1u << 6)
#define IT_RF1L (1u << 7)
#define IT_TC (1u << 9)     // transmission completed
#define IT_TCF (1u << 10)   // transmission cancellation finished
#define IT_EW (1u << 24)
#define IT_EP (1u << 23)
#define IT_BO (1u << 25)
#define IT_RX0 (IT_RF0N | IT_RF0F | IT_RF0L)
#define IT_RX1 (IT_RF1N | IT_RF1F | IT_RF1L)
#define IT_ERR (IT_EW | IT_EP | IT_BO)
#define PSR_EW (1u << 6)
#define PSR_EP (1u << 5)
#define PSR_BO (1u << 7)
#define EL_XTD (1u << 30)
#define EL_RTR (1u << 29)

#define RX_LEN (64)   // RX FIFO 0 elements (the board's message RAM gives FIFO 0 up to 64)
#define TX_LEN (16)   // TX buffers (machine.CAN's TX_QUEUE_LEN on FDCAN)
#define TX_EMPTY (0xFFFFFFFFu)

static const uint8_t dlc_bytes[16] = {0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64};

typedef struct {
    // the controller's registers (memory here)
    volatile uint32_t IR, IE, ILS, ILE, PSR, ECR;
    volatile uint32_t RXF0S, RXF1S;  // fill level bits 0-6, get index bits 8-13, put index 16-21
    volatile uint32_t TXBRP, TXBAR, TXBTO, TXBCF, TXBTIE, TXBCIE;
    // the message RAM
    uint32_t rx0[RX_LEN][4];
    uint32_t tx[TX_LEN][4];
} fdcan_regs_t;

typedef struct {
    mp_obj_base_t base;
    mp_irq_obj_t *irq;
    uint32_t trigger;
    uint8_t started;
    uint8_t state_pending;
    uint32_t rx_errors;
    uint32_t tx_ids[TX_LEN];
    uint32_t n_warning, n_passive, n_bus_off, rx_overruns;
    mp_int_t sent, last_id, last_len, isr_runs;
    fdcan_regs_t r;
} memcan_obj_t;

static void check_started(memcan_obj_t *self) {
    if (!self->started) {
        mp_raise_OSError(MP_EPERM);
    }
}

// What the HAL's notification switch does: line assignment, line enable, the TX
// buffers' own enables, the interrupt enable.
static void activate(memcan_obj_t *self, uint32_t its, uint32_t bufs) {
    fdcan_regs_t *r = &self->r;
    if (!self->started) {
        return;
    }
    if ((r->ILS & its) != 0) {
        r->ILE |= 2;
    } else {
        r->ILE |= 1;
    }
    if (its & IT_TC) {
        r->TXBTIE |= bufs;
    }
    if (its & IT_TCF) {
        r->TXBCIE |= bufs;
    }
    r->IE |= its;
}

static void update_irqs(memcan_obj_t *self) {
    fdcan_regs_t *r = &self->r;
    if (self->trigger & IRQ_RX) {
        activate(self, IT_RX0, 0);
        activate(self, IT_RX1, 0);
    } else {
        r->IE &= ~(IT_RX0 | IT_RX1);
    }
    if (self->trigger & IRQ_TX) {
        r->IE |= IT_TC | IT_TCF;
    } else {
        r->IE &= ~(IT_TC | IT_TCF);
    }
    if (self->trigger & IRQ_STATE) {
        activate(self, IT_ERR, 0);
    } else {
        r->IE &= ~IT_ERR;
    }
}

// --- mp_irq methods: flags() asks the port what fired -----------------------------------
static mp_uint_t memcan_irq_trigger(mp_obj_t self_in, mp_uint_t trigger) {
    memcan_obj_t *self = MP_OBJ_TO_PTR(self_in);
    check_started(self);
    self->trigger = trigger;
    update_irqs(self);
    return 0;
}

static int tx_finished(memcan_obj_t *self, bool *ok) {
    fdcan_regs_t *r = &self->r;
    uint32_t enabled = r->TXBTIE;
    uint32_t done = r->TXBTO & enabled;
    uint32_t cancelled = r->TXBCF & enabled;
    int k = -1;
    for (int i = 0; i < TX_LEN; i++) {
        uint32_t bit = 1u << i;
        if (done & bit) {
            *ok = true;
            k = i;
            break;
        }
        if (cancelled & bit) {
            *ok = false;
            k = i;
            break;
        }
    }
    if (k >= 0) {
        r->TXBTIE &= ~(1u << k);
        r->TXBCIE &= ~(1u << k);
        r->TXBTO &= ~(1u << k);  // (the hardware's occurrence bit stays until the next request)
        r->TXBCF &= ~(1u << k);
        self->tx_ids[k] = TX_EMPTY;
    }
    r->IE |= IT_TC | IT_TCF;
    return k;
}

static mp_uint_t memcan_irq_info(mp_obj_t self_in, mp_uint_t info_type) {
    memcan_obj_t *self = MP_OBJ_TO_PTR(self_in);
    check_started(self);
    if (info_type == MP_IRQ_INFO_TRIGGERS) {
        return self->trigger;
    }
    if (info_type != MP_IRQ_INFO_FLAGS) {
        return 0;
    }
    mp_uint_t f = 0;
    fdcan_regs_t *r = &self->r;
    if ((self->trigger & IRQ_STATE) && self->state_pending) {
        f |= IRQ_STATE;
        self->state_pending = 0;
    }
    if (self->trigger & IRQ_RX) {
        if (r->RXF0S & 0x7F) {
            f |= IRQ_RX;
        }
        if (r->RXF1S & 0x7F) {
            f |= IRQ_RX;
        }
    }
    if (self->trigger & IRQ_TX) {
        bool ok = false;
        int k = tx_finished(self, &ok);
        if (k >= 0) {
            f |= ((mp_uint_t)k << IRQ_IDX_SHIFT) | IRQ_TX | (ok ? 0 : IRQ_TX_FAILED);
        }
    }
    return f;
}

static const mp_irq_methods_t memcan_irq_methods = {
    .trigger = memcan_irq_trigger,
    .info = memcan_irq_info,
};

// --- the interrupt service routine (FDCAN1 line 0) --------------------------------------
static void dispatch(memcan_obj_t *self) {
    if (self->irq != NULL) {
        mp_irq_handler(self->irq);
    }
}

static void isr(memcan_obj_t *self) {
    fdcan_regs_t *r = &self->r;
    self->isr_runs += 1;
    uint32_t ints = r->IR & r->IE;
    uint32_t rx = ints & IT_RX0;
    uint32_t err = ints & IT_ERR;
    uint32_t tx = ints & (IT_TC | IT_TCF);
    r->IE &= ~rx;  // RX masked until recv() takes the frame
    r->IR &= ~(rx | err | tx);  // (write 1 to clear on the controller)
    if (rx) {
        if (rx & IT_RF0F) {
            self->rx_errors |= 1;
        }
        if (rx & IT_RF0L) {
            self->rx_errors |= RECV_ERR_OVERRUN;
            self->rx_overruns += 1;
        }
        if ((rx & IT_RF0N) && (self->trigger & IRQ_RX)) {
            dispatch(self);
        }
    }
    if (err) {
        uint32_t psr = r->PSR;
        if (psr & PSR_BO) {
            self->n_bus_off += 1;
        } else if (psr & PSR_EP) {
            self->n_passive += 1;
        } else if (psr & PSR_EW) {
            self->n_warning += 1;
        }
        if (self->trigger & IRQ_STATE) {
            self->state_pending = 1;
            dispatch(self);
        }
    }
    if (tx) {
        r->IE &= ~tx;
        if (self->trigger & IRQ_TX) {
            dispatch(self);
        } else {
            bool ok;
            tx_finished(self, &ok);
        }
    }
}

// --- machine.CAN's methods ------------------------------------------------------------------
static mp_obj_t memcan_make_new(const mp_obj_type_t *type, size_t n_args, size_t n_kw, const mp_obj_t *args) {
    mp_arg_check_num(n_args, n_kw, 0, 0, false);
    memcan_obj_t *self = mp_obj_malloc(memcan_obj_t, type);
    memset(&self->r, 0, sizeof(self->r));
    self->irq = NULL;
    self->trigger = 0;
    self->started = 1;
    self->state_pending = 0;
    self->rx_errors = 0;
    for (int i = 0; i < TX_LEN; i++) {
        self->tx_ids[i] = TX_EMPTY;
    }
    self->n_warning = self->n_passive = self->n_bus_off = self->rx_overruns = 0;
    self->sent = self->last_id = self->last_len = self->isr_runs = 0;
    return MP_OBJ_FROM_PTR(self);
}

static mp_obj_t memcan_irq(size_t n_args, const mp_obj_t *pos_args, mp_map_t *kw_args) {
    enum { ARG_handler, ARG_trigger, ARG_hard };
    static const mp_arg_t allowed_args[] = {
        { MP_QSTR_handler, MP_ARG_OBJ, {.u_rom_obj = MP_ROM_NONE} },
        { MP_QSTR_trigger, MP_ARG_INT, {.u_int = 0} },
        { MP_QSTR_hard, MP_ARG_BOOL, {.u_bool = false} },
    };
    memcan_obj_t *self = MP_OBJ_TO_PTR(pos_args[0]);
    check_started(self);
    mp_arg_val_t args[MP_ARRAY_SIZE(allowed_args)];
    mp_arg_parse_all(n_args - 1, pos_args + 1, kw_args, MP_ARRAY_SIZE(allowed_args), allowed_args, args);
    if (self->irq == NULL) {
        self->trigger = 0;
        self->irq = mp_irq_new(&memcan_irq_methods, MP_OBJ_FROM_PTR(self));
    }
    if (n_args > 1 || kw_args->used != 0) {
        mp_obj_t handler = args[ARG_handler].u_obj;
        if (handler != mp_const_none && !mp_obj_is_callable(handler)) {
            mp_raise_ValueError(MP_ERROR_TEXT("handler must be None or callable"));
        }
        self->irq->handler = handler;
        self->irq->ishard = args[ARG_hard].u_bool;
        memcan_irq_trigger(MP_OBJ_FROM_PTR(self), args[ARG_trigger].u_int);
    }
    return MP_OBJ_FROM_PTR(self->irq);
}
static MP_DEFINE_CONST_FUN_OBJ_KW(memcan_irq_obj, 1, memcan_irq);

// One frame out of RX FIFO 0 (FIFO 1 is looked at too, as the board does): false if empty.
static bool take_frame(memcan_obj_t *self, uint8_t *data, size_t *dlen, mp_uint_t *id, mp_uint_t *flags) {
    fdcan_regs_t *r = &self->r;
    for (int fifo = 0; fifo < 2; fifo++) {
        volatile uint32_t *s = fifo == 0 ? &r->RXF0S : &r->RXF1S;
        if ((*s & 0x7F) == 0) {
            continue;
        }
        uint32_t get = (*s >> 8) & 0x3F;
        const uint32_t *el = r->rx0[get];  // (FIFO 1 has no elements in this model)
        uint32_t w0 = el[0];
        uint32_t w1 = el[1];
        *id = (w0 & EL_XTD) ? (w0 & 0x1FFFFFFF) : ((w0 >> 18) & 0x7FF);
        *flags = ((w0 & EL_XTD) ? FLAG_EXT_ID : 0) | ((w0 & EL_RTR) ? FLAG_RTR : 0);
        size_t n = dlc_bytes[(w1 >> 16) & 0xF];
        const uint8_t *src = (const uint8_t *)&el[2];
        for (size_t i = 0; i < n; i++) {
            data[i] = src[i];
        }
        *dlen = n;
        // acknowledge: the get index moves on, the fill level drops
        uint32_t fill = (*s & 0x7F) - 1;
        uint32_t nget = (get + 1) % RX_LEN;
        *s = (*s & ~0x3F7Fu) | (nget << 8) | fill;
        activate(self, fifo == 0 ? IT_RX0 : IT_RX1, 0);  // the RX interrupt again
        return true;
    }
    return false;
}

static mp_obj_t memcan_recv(size_t n_args, const mp_obj_t *args) {
    memcan_obj_t *self = MP_OBJ_TO_PTR(args[0]);
    check_started(self);
    if (n_args < 2 || args[1] == mp_const_none) {
        mp_raise_ValueError(MP_ERROR_TEXT("memcan: recv needs its list"));  // (jig.canport always passes one)
    }
    mp_obj_list_t *lst = mp_obj_list_optional_arg(args[1], 4);
    mp_obj_t *items = lst->items;
    if (!mp_obj_is_type(items[1], &mp_type_memoryview)) {
        mp_raise_TypeError(NULL);
    }
    uint8_t data[8];
    size_t dlen = 0;
    mp_uint_t id = 0;
    mp_uint_t flags = 0;
    if (!take_frame(self, data, &dlen, &id, &flags)) {
        return mp_const_none;
    }
    mp_uint_t errors = self->rx_errors;
    self->rx_errors = 0;
    mp_obj_array_t *mv = MP_OBJ_TO_PTR(items[1]);
    if (flags & FLAG_RTR) {
        memset(mv->items, 0, dlen);
    } else {
        memcpy(mv->items, data, dlen);
    }
    mv->len = dlen;
    items[0] = MP_OBJ_NEW_SMALL_INT(id);
    items[2] = MP_OBJ_NEW_SMALL_INT(flags);
    items[3] = MP_OBJ_NEW_SMALL_INT(errors);
    return MP_OBJ_FROM_PTR(lst);
}
static MP_DEFINE_CONST_FUN_OBJ_VAR_BETWEEN(memcan_recv_obj, 1, 2, memcan_recv);

static mp_obj_t memcan_send(size_t n_args, const mp_obj_t *pos_args, mp_map_t *kw_args) {
    enum { ARG_id, ARG_data, ARG_flags };
    static const mp_arg_t allowed_args[] = {
        { MP_QSTR_id, MP_ARG_REQUIRED | MP_ARG_INT, {} },
        { MP_QSTR_data, MP_ARG_REQUIRED | MP_ARG_OBJ, {} },
        { MP_QSTR_flags, MP_ARG_INT, {.u_int = 0} },
    };
    memcan_obj_t *self = MP_OBJ_TO_PTR(pos_args[0]);
    check_started(self);
    mp_arg_val_t args[MP_ARRAY_SIZE(allowed_args)];
    mp_arg_parse_all(n_args - 1, pos_args + 1, kw_args, MP_ARRAY_SIZE(allowed_args), allowed_args, args);
    mp_uint_t id = args[ARG_id].u_int;
    mp_uint_t flags = args[ARG_flags].u_int;
    mp_buffer_info_t data;
    mp_get_buffer_raise(args[ARG_data].u_obj, &data, MP_BUFFER_READ);
    if (data.len > 8) {
        mp_raise_msg(&mp_type_OverflowError, MP_ERROR_TEXT("data too long"));
    }
    if (id > ((flags & FLAG_EXT_ID) ? 0x1FFFFFFFu : 0x7FFu)) {
        mp_raise_ValueError(MP_ERROR_TEXT("invalid id"));
    }
    // a free TX buffer with no equal id queued (unless FLAG_UNORDERED)
    int free_k = -1;
    for (int i = 0; i < TX_LEN; i++) {
        uint32_t q = self->tx_ids[i];
        if (q == TX_EMPTY) {
            if (free_k < 0) {
                free_k = i;
            }
        } else if (q == id && !(flags & 16)) {
            return mp_const_none;
        }
    }
    if (free_k < 0) {
        return mp_const_none;
    }
    uint32_t dlc = 0;
    for (uint32_t i = 0; i < 16; i++) {
        if (data.len <= dlc_bytes[i]) {
            dlc = i;
            break;
        }
    }
    fdcan_regs_t *r = &self->r;
    uint32_t loc = 1u << free_k;
    activate(self, IT_TC | IT_TCF, loc);
    if (r->TXBRP & loc) {
        return mp_const_none;
    }
    uint32_t *el = r->tx[free_k];
    el[0] = (flags & FLAG_EXT_ID) ? (EL_XTD | id) : (id << 18);
    if (flags & FLAG_RTR) {
        el[0] |= EL_RTR;
    }
    el[1] = dlc << 16;
    const uint8_t *src = data.buf;
    for (size_t i = 0; i < data.len; i += 4) {
        uint32_t w = 0;
        for (size_t j = 0; j < 4 && i + j < data.len; j++) {
            w |= (uint32_t)src[i + j] << (8 * j);
        }
        el[2 + i / 4] = w;
    }
    r->TXBAR = loc;
    r->TXBRP |= loc;  // (the controller: pending until it has gone)
    self->tx_ids[free_k] = id;
    self->sent += 1;
    self->last_id = id;
    self->last_len = data.len;
    return MP_OBJ_NEW_SMALL_INT(free_k);
}
static MP_DEFINE_CONST_FUN_OBJ_KW(memcan_send_obj, 3, memcan_send);

static mp_obj_t memcan_state(mp_obj_t self_in) {
    memcan_obj_t *self = MP_OBJ_TO_PTR(self_in);
    if (!self->started) {
        return MP_OBJ_NEW_SMALL_INT(0);
    }
    uint32_t psr = self->r.PSR;
    return MP_OBJ_NEW_SMALL_INT((psr & PSR_BO) ? 4 : (psr & PSR_EP) ? 3 : (psr & PSR_EW) ? 2 : 1);
}
static MP_DEFINE_CONST_FUN_OBJ_1(memcan_state_obj, memcan_state);

static mp_obj_t memcan_get_counters(size_t n_args, const mp_obj_t *args) {
    memcan_obj_t *self = MP_OBJ_TO_PTR(args[0]);
    mp_obj_list_t *lst = mp_obj_list_optional_arg(n_args > 1 ? args[1] : mp_const_none, 8);
    check_started(self);
    fdcan_regs_t *r = &self->r;
    uint32_t ecr = r->ECR;
    uint32_t tec = ecr & 0xFF;
    uint32_t rec = (ecr & (1u << 15)) ? 128 : ((ecr >> 8) & 0x7F);
    uint32_t pending = 0;
    for (uint32_t b = r->TXBRP; b != 0; b &= b - 1) {
        pending += 1;
    }
    mp_obj_t *it = lst->items;
    it[0] = MP_OBJ_NEW_SMALL_INT(tec);
    it[1] = MP_OBJ_NEW_SMALL_INT(rec);
    it[2] = MP_OBJ_NEW_SMALL_INT(self->n_warning);
    it[3] = MP_OBJ_NEW_SMALL_INT(self->n_passive);
    it[4] = MP_OBJ_NEW_SMALL_INT(self->n_bus_off);
    it[5] = MP_OBJ_NEW_SMALL_INT(pending);
    it[6] = MP_OBJ_NEW_SMALL_INT((r->RXF0S & 0x7F) + (r->RXF1S & 0x7F));
    it[7] = MP_OBJ_NEW_SMALL_INT(self->rx_overruns);
    return MP_OBJ_FROM_PTR(lst);
}
static MP_DEFINE_CONST_FUN_OBJ_VAR_BETWEEN(memcan_get_counters_obj, 1, 2, memcan_get_counters);

static mp_obj_t memcan_set_filters(mp_obj_t self_in, mp_obj_t filters) {
    (void)filters;
    check_started(MP_OBJ_TO_PTR(self_in));
    return mp_const_none;
}
static MP_DEFINE_CONST_FUN_OBJ_2(memcan_set_filters_obj, memcan_set_filters);

static mp_obj_t memcan_restart(mp_obj_t self_in) {
    memcan_obj_t *self = MP_OBJ_TO_PTR(self_in);
    check_started(self);
    for (int i = 0; i < TX_LEN; i++) {
        self->tx_ids[i] = TX_EMPTY;
    }
    self->r.TXBRP = 0;
    self->r.PSR = 0;
    self->state_pending = 0;
    return mp_const_none;
}
static MP_DEFINE_CONST_FUN_OBJ_1(memcan_restart_obj, memcan_restart);

static mp_obj_t memcan_deinit(mp_obj_t self_in) {
    memcan_obj_t *self = MP_OBJ_TO_PTR(self_in);
    self->started = 0;
    self->r.IE = 0;
    return mp_const_none;
}
static MP_DEFINE_CONST_FUN_OBJ_1(memcan_deinit_obj, memcan_deinit);

// --- the rig's side: the bus and the controller ---------------------------------------------
static void put_frame(memcan_obj_t *self, size_t n_args, const mp_obj_t *args) {
    fdcan_regs_t *r = &self->r;
    mp_uint_t id = mp_obj_get_int(args[1]);
    mp_buffer_info_t info;
    mp_get_buffer_raise(args[2], &info, MP_BUFFER_READ);
    size_t n = mp_obj_get_int(args[3]);
    mp_uint_t flags = mp_obj_get_int(args[4]);
    if (n > 8 || n > info.len) {
        mp_raise_ValueError(MP_ERROR_TEXT("bus_rx: length"));
    }
    uint32_t fill = r->RXF0S & 0x7F;
    if (fill == RX_LEN) {
        r->IR |= IT_RF0L;
        return;
    }
    uint32_t put = (r->RXF0S >> 16) & 0x3F;
    uint32_t *el = r->rx0[put];
    el[0] = (flags & FLAG_EXT_ID) ? (EL_XTD | id) : (id << 18);
    if (flags & FLAG_RTR) {
        el[0] |= EL_RTR;
    }
    el[1] = n << 16;
    el[2] = el[3] = 0;
    memcpy(&el[2], info.buf, n);
    fill += 1;
    r->RXF0S = (r->RXF0S & ~0x3F007Fu) | (((put + 1) % RX_LEN) << 16) | fill;
    r->IR |= IT_RF0N | (fill == RX_LEN ? IT_RF0F : 0);
}

static mp_obj_t memcan_bus_rx(size_t n_args, const mp_obj_t *args) {
    memcan_obj_t *self = MP_OBJ_TO_PTR(args[0]);
    put_frame(self, n_args, args);
    if (self->r.IR & self->r.IE) {
        isr(self);
    }
    return mp_const_none;
}
static MP_DEFINE_CONST_FUN_OBJ_VAR_BETWEEN(memcan_bus_rx_obj, 5, 5, memcan_bus_rx);

static mp_obj_t memcan_bus_put(size_t n_args, const mp_obj_t *args) {
    memcan_obj_t *self = MP_OBJ_TO_PTR(args[0]);
    put_frame(self, n_args, args);
    return mp_const_none;  // (no ISR: this is the rig's own share)
}
static MP_DEFINE_CONST_FUN_OBJ_VAR_BETWEEN(memcan_bus_put_obj, 5, 5, memcan_bus_put);

static mp_obj_t memcan_bus_clear(mp_obj_t self_in) {
    memcan_obj_t *self = MP_OBJ_TO_PTR(self_in);
    self->r.RXF0S = 0;
    self->r.IR &= ~(IT_RX0);
    return mp_const_none;
}
static MP_DEFINE_CONST_FUN_OBJ_1(memcan_bus_clear_obj, memcan_bus_clear);

static mp_obj_t memcan_bus_tx_done(mp_obj_t self_in, mp_obj_t ok_in) {
    memcan_obj_t *self = MP_OBJ_TO_PTR(self_in);
    fdcan_regs_t *r = &self->r;
    uint32_t pending = r->TXBRP;
    r->TXBRP = 0;
    if (mp_obj_is_true(ok_in)) {
        r->TXBTO |= pending;
    } else {
        r->TXBCF |= pending;
    }
    if (pending) {
        r->IR |= IT_TC;
    }
    if (r->IR & r->IE) {
        isr(self);
    }
    return mp_const_none;
}
static MP_DEFINE_CONST_FUN_OBJ_2(memcan_bus_tx_done_obj, memcan_bus_tx_done);

static mp_obj_t memcan_bus_nop(mp_obj_t self_in, mp_obj_t x) {
    (void)self_in;
    (void)x;
    return mp_const_none;
}
static MP_DEFINE_CONST_FUN_OBJ_2(memcan_bus_nop_obj, memcan_bus_nop);

static void memcan_attr(mp_obj_t self_in, qstr attr, mp_obj_t *dest) {
    memcan_obj_t *self = MP_OBJ_TO_PTR(self_in);
    if (dest[0] != MP_OBJ_NULL) {
        return;  // read-only
    }
    if (attr == MP_QSTR_sent) {
        dest[0] = mp_obj_new_int(self->sent);
    } else if (attr == MP_QSTR_last_id) {
        dest[0] = mp_obj_new_int(self->last_id);
    } else if (attr == MP_QSTR_last_len) {
        dest[0] = mp_obj_new_int(self->last_len);
    } else if (attr == MP_QSTR_isr_runs) {
        dest[0] = mp_obj_new_int(self->isr_runs);
    } else if (attr == MP_QSTR_rx_fill) {
        dest[0] = mp_obj_new_int(self->r.RXF0S & 0x7F);
    } else {
        dest[1] = MP_OBJ_SENTINEL;  // methods and constants: from the locals dict
    }
}

static const mp_rom_map_elem_t memcan_locals_dict_table[] = {
    { MP_ROM_QSTR(MP_QSTR_irq), MP_ROM_PTR(&memcan_irq_obj) },
    { MP_ROM_QSTR(MP_QSTR_recv), MP_ROM_PTR(&memcan_recv_obj) },
    { MP_ROM_QSTR(MP_QSTR_send), MP_ROM_PTR(&memcan_send_obj) },
    { MP_ROM_QSTR(MP_QSTR_state), MP_ROM_PTR(&memcan_state_obj) },
    { MP_ROM_QSTR(MP_QSTR_get_counters), MP_ROM_PTR(&memcan_get_counters_obj) },
    { MP_ROM_QSTR(MP_QSTR_set_filters), MP_ROM_PTR(&memcan_set_filters_obj) },
    { MP_ROM_QSTR(MP_QSTR_restart), MP_ROM_PTR(&memcan_restart_obj) },
    { MP_ROM_QSTR(MP_QSTR_deinit), MP_ROM_PTR(&memcan_deinit_obj) },
    { MP_ROM_QSTR(MP_QSTR_bus_rx), MP_ROM_PTR(&memcan_bus_rx_obj) },
    { MP_ROM_QSTR(MP_QSTR_bus_put), MP_ROM_PTR(&memcan_bus_put_obj) },
    { MP_ROM_QSTR(MP_QSTR_bus_clear), MP_ROM_PTR(&memcan_bus_clear_obj) },
    { MP_ROM_QSTR(MP_QSTR_bus_tx_done), MP_ROM_PTR(&memcan_bus_tx_done_obj) },
    { MP_ROM_QSTR(MP_QSTR_bus_nop), MP_ROM_PTR(&memcan_bus_nop_obj) },
    { MP_ROM_QSTR(MP_QSTR_FLAG_RTR), MP_ROM_INT(FLAG_RTR) },
    { MP_ROM_QSTR(MP_QSTR_FLAG_EXT_ID), MP_ROM_INT(FLAG_EXT_ID) },
    { MP_ROM_QSTR(MP_QSTR_FLAG_UNORDERED), MP_ROM_INT(16) },
    { MP_ROM_QSTR(MP_QSTR_IRQ_TX), MP_ROM_INT(IRQ_TX) },
    { MP_ROM_QSTR(MP_QSTR_IRQ_RX), MP_ROM_INT(IRQ_RX) },
    { MP_ROM_QSTR(MP_QSTR_IRQ_TX_FAILED), MP_ROM_INT(IRQ_TX_FAILED) },
    { MP_ROM_QSTR(MP_QSTR_IRQ_STATE), MP_ROM_INT(IRQ_STATE) },
    { MP_ROM_QSTR(MP_QSTR_STATE_ACTIVE), MP_ROM_INT(1) },
};
static MP_DEFINE_CONST_DICT(memcan_locals_dict, memcan_locals_dict_table);

MP_DEFINE_CONST_OBJ_TYPE(
    memcan_type_CAN,
    MP_QSTR_CAN,
    MP_TYPE_FLAG_NONE,
    make_new, memcan_make_new,
    attr, memcan_attr,
    locals_dict, &memcan_locals_dict
    );

// --- the SLCAN port (USB_VCP's any/readinto/write) --------------------------------------------
enum { V_ANY, V_READ, V_WRITE, V_LOAD, V_COUNT };

typedef struct {
    mp_obj_base_t base;
    mp_obj_t counts_obj;
    int32_t *counts;
    size_t n;
    size_t pos;
    mp_int_t taken;
    uint8_t rx[64];
} memvcp_obj_t;

static memvcp_obj_t *vcp_of(mp_obj_t self_in, int k) {
    memvcp_obj_t *self = MP_OBJ_TO_PTR(self_in);
    self->counts[k] += 1;
    return self;
}

static mp_obj_t memvcp_make_new(const mp_obj_type_t *type, size_t n_args, size_t n_kw, const mp_obj_t *args) {
    mp_arg_check_num(n_args, n_kw, 1, 1, false);
    mp_buffer_info_t info;
    mp_get_buffer_raise(args[0], &info, MP_BUFFER_RW);
    if (info.typecode != 'i' || info.len < V_COUNT * sizeof(int32_t)) {
        mp_raise_ValueError(MP_ERROR_TEXT("counts: array('i') of 4"));
    }
    memvcp_obj_t *self = mp_obj_malloc(memvcp_obj_t, type);
    self->counts_obj = args[0];
    self->counts = info.buf;
    self->n = self->pos = 0;
    self->taken = 0;
    return MP_OBJ_FROM_PTR(self);
}

static mp_obj_t memvcp_any(mp_obj_t self_in) {
    memvcp_obj_t *self = vcp_of(self_in, V_ANY);
    return MP_OBJ_NEW_SMALL_INT(self->n - self->pos);
}
static MP_DEFINE_CONST_FUN_OBJ_1(memvcp_any_obj, memvcp_any);

static mp_obj_t memvcp_readinto(mp_obj_t self_in, mp_obj_t buf_in) {
    memvcp_obj_t *self = vcp_of(self_in, V_READ);
    mp_buffer_info_t info;
    mp_get_buffer_raise(buf_in, &info, MP_BUFFER_WRITE);
    size_t k = self->n - self->pos;
    if (k > info.len) {
        k = info.len;
    }
    memcpy(info.buf, self->rx + self->pos, k);
    self->pos += k;
    return MP_OBJ_NEW_SMALL_INT(k);
}
static MP_DEFINE_CONST_FUN_OBJ_2(memvcp_readinto_obj, memvcp_readinto);

static mp_obj_t memvcp_write(mp_obj_t self_in, mp_obj_t buf_in) {
    memvcp_obj_t *self = vcp_of(self_in, V_WRITE);
    mp_buffer_info_t info;
    mp_get_buffer_raise(buf_in, &info, MP_BUFFER_READ);
    self->taken += info.len;
    return MP_OBJ_NEW_SMALL_INT(info.len);
}
static MP_DEFINE_CONST_FUN_OBJ_2(memvcp_write_obj, memvcp_write);

static mp_obj_t memvcp_load(mp_obj_t self_in, mp_obj_t data_in, mp_obj_t n_in) {
    memvcp_obj_t *self = vcp_of(self_in, V_LOAD);
    mp_buffer_info_t info;
    mp_get_buffer_raise(data_in, &info, MP_BUFFER_READ);
    size_t n = mp_obj_get_int(n_in);
    if (n > sizeof(self->rx) || n > info.len) {
        mp_raise_ValueError(MP_ERROR_TEXT("load: length"));
    }
    memcpy(self->rx, info.buf, n);
    self->n = n;
    self->pos = 0;
    return mp_const_none;
}
static MP_DEFINE_CONST_FUN_OBJ_3(memvcp_load_obj, memvcp_load);

static mp_obj_t memvcp_again(mp_obj_t self_in) {
    memvcp_obj_t *self = vcp_of(self_in, V_LOAD);
    self->pos = 0;
    return mp_const_none;
}
static MP_DEFINE_CONST_FUN_OBJ_1(memvcp_again_obj, memvcp_again);

static void memvcp_attr(mp_obj_t self_in, qstr attr, mp_obj_t *dest) {
    memvcp_obj_t *self = MP_OBJ_TO_PTR(self_in);
    if (dest[0] == MP_OBJ_NULL && attr == MP_QSTR_taken) {
        dest[0] = mp_obj_new_int(self->taken);
    } else {
        dest[1] = MP_OBJ_SENTINEL;
    }
}

static const mp_rom_map_elem_t memvcp_locals_dict_table[] = {
    { MP_ROM_QSTR(MP_QSTR_any), MP_ROM_PTR(&memvcp_any_obj) },
    { MP_ROM_QSTR(MP_QSTR_readinto), MP_ROM_PTR(&memvcp_readinto_obj) },
    { MP_ROM_QSTR(MP_QSTR_write), MP_ROM_PTR(&memvcp_write_obj) },
    { MP_ROM_QSTR(MP_QSTR_load), MP_ROM_PTR(&memvcp_load_obj) },
    { MP_ROM_QSTR(MP_QSTR_again), MP_ROM_PTR(&memvcp_again_obj) },
};
static MP_DEFINE_CONST_DICT(memvcp_locals_dict, memvcp_locals_dict_table);

MP_DEFINE_CONST_OBJ_TYPE(
    memcan_type_Vcp,
    MP_QSTR_Vcp,
    MP_TYPE_FLAG_NONE,
    make_new, memvcp_make_new,
    attr, memvcp_attr,
    locals_dict, &memvcp_locals_dict
    );

static const mp_rom_map_elem_t memcan_module_globals_table[] = {
    { MP_ROM_QSTR(MP_QSTR___name__), MP_ROM_QSTR(MP_QSTR_memcan) },
    { MP_ROM_QSTR(MP_QSTR_CAN), MP_ROM_PTR(&memcan_type_CAN) },
    { MP_ROM_QSTR(MP_QSTR_Vcp), MP_ROM_PTR(&memcan_type_Vcp) },
};
static MP_DEFINE_CONST_DICT(memcan_module_globals, memcan_module_globals_table);

const mp_obj_module_t memcan_module = {
    .base = { &mp_type_module },
    .globals = (mp_obj_dict_t *)&memcan_module_globals,
};

MP_REGISTER_MODULE(MP_QSTR_memcan, memcan_module);
